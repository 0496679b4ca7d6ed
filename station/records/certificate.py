"""Calibration certificate of one DUT (issues 13 and 22): what was measured on which station, by
whom, with which firmware, profile and limits version; the coefficients with their expanded
uncertainty; EVERY check the verdict used (failing first); program-and-verify when done; and the
statements ISO/IEC 17025:2017 clause 7.8 asks of a calibration certificate: unique id and "page x
of y", issuer and authorising person, the model equation, the uncertainty statement (U = k u,
k = 2), the decision rule behind the verdict, traceability and environmental conditions.

Three layers, as elsewhere in the station:
- `build_certificate(...)` is the pure core: stored rows (plain dicts, as db.repository gives them)
  in, a typed `Certificate` out. No database, no files, no matplotlib; a unit test gives it dicts.
- `certificate_rows(cert)` and `paginate(rows)` are the pure layout: the certificate as rows of
  known height (inches), split over as many A4 pages as they need. A page holds what its height
  holds, a table that goes on repeats its header, and nothing is ever cut off: the number of pages
  is known before drawing, so every page can say "page x of y".
- `certificate_for(db, serial)` reads the rows (the DUT's latest valid attempt, the same run
  `GET /api/duts/{serial}` reports) and `render_pdf(cert)` draws the pages with matplotlib's PDF
  backend (object API and PdfPages, no pyplot state, so the web's thread pool may call it).

Who issues the certificate (`[certificate]` in the station config: issuer, address, authorised_by,
reference_thermometer) is read from the config snapshot stored with the run's batch: the same
record always prints the same certificate, and a station that never configured it prints "not
configured" instead of a made-up name. The CLI may pass a config's section instead.

The fit plot shows, per axis, the stable segments' mean acceleration against temperature (each
orientation relative to its own level at T_ref) with the thermal model's line through them
(martinez2022 eq. 1): the reader sees the points the coefficients came from.
"""

from __future__ import annotations

import io
import math
import re
import textwrap
import threading
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from typing import Any, Iterable

from station.science.thermal_model import FULL_SCALE_MG
from contracts.types import AXES, T_REF_C

_LOCK = threading.Lock()  # matplotlib's text layout is not fully thread safe (as web/plots.py)

COVERAGE_K = 2.0  # coverage factor of the expanded uncertainty U = k u (about 95 % for a normal law)
DEFAULT_GUARD_SIGMA = 2.0  # spec_limits.ProductSpec.guard_sigma's default, when the stored config lacks the set
NOT_CONFIGURED = "not configured"
# martinez2022 eq. 1 as the station implements it (station/science/thermal_model.py: apply_drift)
MODEL_EQUATION = "Acc(T) = Acc0 · (1 + TDSF · (T - Tref)) + TDB · (T - Tref)"
# worst first: a reader of page 1 sees what failed (the rank of station/decisions/verdicts.py)
OUTCOME_ORDER = ("error", "fail", "marginal", "pass")
FLAG_CHECKS = frozenset({"program_crc_match", "compensation_on"})  # 1 = yes, 0 = no


@dataclass(frozen=True)
class Coefficient:
    """One calibrated coefficient: value, its measured 1-sigma (None when the method gives none),
    and `u_combined`, the combined standard uncertainty the verdict judged it with (the measured
    sigma and the limits set's systematic u_sys in quadrature; None when no check judged it)."""

    name: str  # "TDB", "TDSF", "SFEM bias", ...
    axis: str
    value: float | None
    sigma: float | None
    unit: str
    method: str = ""
    note: str = ""  # e.g. "clamped" (TDSF held at 0: not observable in this run)
    u_combined: float | None = None

    @property
    def u(self) -> float | None:
        """The standard uncertainty the certificate states (combined when known)."""
        return self.u_combined if self.u_combined is not None else self.sigma

    @property
    def expanded_u(self) -> float | None:
        """U = k u, k = COVERAGE_K."""
        return None if self.u is None else COVERAGE_K * self.u


@dataclass(frozen=True)
class FitPoint:
    """One stable segment for the fit plot: temperature and mean acceleration per axis (g)."""

    temp_c: float
    acc_g: tuple[float, float, float]
    orientation: int


@dataclass(frozen=True)
class Issuer:
    """`[certificate]` of the station config: who issues and authorises the certificates. An
    empty field is printed as "not configured", never filled in."""

    issuer: str = ""
    address: str = ""
    authorised_by: str = ""
    reference_thermometer: str = ""  # the plate thermometer's own calibration, in the config's words


@dataclass(frozen=True)
class Environment:
    """What the station stored about the conditions of the run (the rest is "not recorded")."""

    dut_temp_min_c: float | None = None  # board temperature sensor, stable segments
    dut_temp_max_c: float | None = None
    n_segments: int = 0
    verify_temp_from_c: float | None = None  # the verification heat (program and verify)
    verify_temp_to_c: float | None = None
    plate_thermometer: str | None = None  # its link, when the batch's config had one


@dataclass
class Certificate:
    serial: str
    sensor: str
    firmware: str
    run_id: int
    batch_id: int
    attempt: int | None
    station: str
    operator: str
    profile: str
    limits_name: str | None
    limits_version: str | None
    started_at: str | None
    ended_at: str | None
    judged_at: str | None
    verdict: str | None
    grade: str | None
    tray: str | None
    reason: str | None
    thermal_method: str | None
    coefficients: list[Coefficient] = field(default_factory=list)
    checks: list[dict] = field(default_factory=list)  # EVERY check of the verdict, worst first
    program_verify: dict | None = None
    verification: dict | None = None  # the stored verification (verify.VerificationResult.to_json())
    fit_points: list[FitPoint] = field(default_factory=list)
    issued_at: str = ""
    revision: int | None = None  # of the verdict record (1 = first final verdict; None: not judged)
    certificate_id: str = ""
    issuer: Issuer = field(default_factory=Issuer)
    guard_sigma: float = DEFAULT_GUARD_SIGMA
    guard_sigma_stored: bool = False  # False: the limits set is not in the stored config (default used)
    environment: Environment = field(default_factory=Environment)
    software_version: str = ""  # the issuing station software
    schema_version: str | None = None  # the database schema the run was stored with

    def coefficient(self, name: str, axis: str) -> Coefficient | None:
        return next((c for c in self.coefficients if c.name == name and c.axis == axis), None)

    def outcome_counts(self) -> dict[str, int]:
        counts: dict[str, int] = {}
        for c in self.checks:
            o = str(c.get("outcome") or "")
            counts[o] = counts.get(o, 0) + 1
        return counts

    def to_json(self) -> dict:
        return asdict(self)


# ---- pure core ---------------------------------------------------------------------------------
def _f(v: Any) -> float | None:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def ordered_checks(checks: Iterable[Any]) -> list[dict]:
    """Every check, worst outcome first (error, fail, marginal, pass), the verdict's own order kept
    within an outcome; a check with an outcome the station does not know goes last, never away."""
    rank = {o: i for i, o in enumerate(OUTCOME_ORDER)}
    rows = [c for c in checks if isinstance(c, dict)]
    return sorted(rows, key=lambda c: rank.get(str(c.get("outcome") or ""), len(OUTCOME_ORDER)))


def _check_sigma(checks: list[dict], measurement: str, axis: str) -> float | None:
    c = next((c for c in checks if c.get("measurement") == measurement and c.get("axis") == axis), None)
    return None if c is None else _f(c.get("sigma"))


def _coefficients(thermal_by_method: dict, preferred: str | None, sfem: dict | None,
                  checks: list[dict]) -> list[Coefficient]:
    out: list[Coefficient] = []
    res = (thermal_by_method or {}).get(preferred or "") or {}
    for ax in AXES:
        a = res.get(ax) or {}
        if not a:
            continue
        out.append(Coefficient("TDB", ax, _f(a.get("tdb_mg_per_c")), _f(a.get("tdb_sigma_mg_per_c")), "mg/°C",
                               preferred or "", u_combined=_check_sigma(checks, "tdb_mg_per_c", ax)))
        out.append(Coefficient("TDSF", ax, _f(a.get("tdsf_ppm_per_c")), _f(a.get("tdsf_sigma_ppm_per_c")), "ppm/°C",
                               preferred or "", "clamped to 0 (not observable)" if a.get("tdsf_clamped") else "",
                               u_combined=_check_sigma(checks, "tdsf_ppm_per_c", ax)))
    if isinstance(sfem, dict):
        fit = sfem
        steps = sfem.get("steps")
        if isinstance(steps, list) and steps:
            fit = steps[0] or {}  # the first temperature step (the polynomials are in the JSON record)
        b = fit.get("b") or fit.get("bias_g") or fit.get("bias")
        bs = fit.get("bias_sigma")
        if isinstance(b, (list, tuple)) and len(b) == 3:
            for k, (ax, v) in enumerate(zip(AXES, b)):
                s = _f(bs[k]) if isinstance(bs, (list, tuple)) and len(bs) == 3 else None
                out.append(Coefficient("SFEM bias", ax, None if _f(v) is None else _f(v) * 1e3,
                                       None if s is None else s * 1e3, "mg", "sfem",
                                       u_combined=_check_sigma(checks, "sfem_bias_mg", ax)))
    return out


def certificate_id(station: str, run_id: int, revision: int | None) -> str:
    """Unique and stable: the station, the run and the revision of its verdict record. The same
    record always gets the same id; a record that supersedes it (a resumed batch judged again)
    gets revision N + 1 and so a new id."""
    slug = re.sub(r"[^A-Za-z0-9._-]+", "-", station).strip("-") or "station"
    return f"{slug}-run{run_id}-" + (f"rev{revision}" if revision else "unjudged")


def _guard_sigma(snapshot: dict, limits_name: str | None, limits_version: str | None) -> tuple[float, bool]:
    """The guard band k of the limits set the run was judged by, from the batch's stored config."""
    for spec in ((snapshot or {}).get("products") or {}).values():
        if not isinstance(spec, dict):
            continue
        if spec.get("name") == limits_name and str(spec.get("version")) == str(limits_version):
            g = _f(spec.get("guard_sigma"))
            if g is not None:
                return g, True
    return DEFAULT_GUARD_SIGMA, False


def _modbus_link(dev: Any) -> str | None:
    """The link of a Modbus device of the config snapshot, in the config's terms."""
    if not isinstance(dev, dict):
        return None
    if isinstance(dev.get("tcp"), dict):
        return f"modbus tcp {dev['tcp'].get('host')}:{dev['tcp'].get('port')} unit {dev.get('unit')}"
    if isinstance(dev.get("rtu"), dict):
        return f"modbus rtu {dev['rtu'].get('port')} unit {dev.get('unit')}"
    return "configured"


def _issuer(section: Any) -> Issuer:
    s = section if isinstance(section, dict) else {}
    return Issuer(*(str(s.get(k) or "").strip() for k in ("issuer", "address", "authorised_by",
                                                             "reference_thermometer")))


def _environment(segments: list[dict], verification: dict | None, snapshot: dict) -> Environment:
    temps = [t for t in (_f(g.get("temp_mean_c")) for g in segments or []) if t is not None]
    ver = verification or {}
    return Environment(
        dut_temp_min_c=min(temps) if temps else None, dut_temp_max_c=max(temps) if temps else None,
        n_segments=len(temps), verify_temp_from_c=_f(ver.get("temp_from_c")), verify_temp_to_c=_f(ver.get("temp_to_c")),
        plate_thermometer=_modbus_link((snapshot or {}).get("thermometer")),
    )


def build_certificate(run: dict, batch: dict, segments: list[dict], issued_at: datetime | None = None, *,
                      revision: int | None = None, verification: dict | None = None,
                      certificate_config: dict | None = None, software_version: str = "") -> Certificate:
    """The certificate of one run. run: db.repository.run_detail (with thermal results, verdict
    detail, program_verify); batch: db.repository.batch_detail (station, operator, profile, the
    config snapshot); segments: db.repository.segments_of_run; revision: of the run's verdict
    record (db.repository.revision_of); verification: the stored verification JSON;
    certificate_config: a `[certificate]` section to use instead of the snapshot's."""
    identity = run.get("identity") or {}
    detail = run.get("verdict_detail") or {}
    # every check the verdict stored; a record without the full list still has its failures
    checks = ordered_checks(detail.get("checks") or detail.get("failures") or [])
    snapshot = batch.get("config_snapshot") or {}
    points = []
    for g in segments or []:
        acc = g.get("acc_mean_g")
        t = _f(g.get("temp_mean_c"))
        if isinstance(acc, (list, tuple)) and len(acc) == 3 and t is not None and all(_f(v) is not None for v in acc):
            points.append(FitPoint(t, (float(acc[0]), float(acc[1]), float(acc[2])), int(g.get("orientation") or 0)))
    station = str(batch.get("station") or run.get("station") or "") or "unnamed"
    run_id = int(run["id"])
    guard, guard_stored = _guard_sigma(snapshot, run.get("limits_name"), run.get("limits_version"))
    return Certificate(
        serial=str(run.get("serial") or identity.get("serial") or ""),
        sensor=str(identity.get("sensor") or run.get("sensor") or ""),
        firmware=str(identity.get("fw") or identity.get("firmware") or "") or "not reported",
        run_id=run_id,
        batch_id=int(run.get("batch_id") or 0),
        attempt=run.get("attempt"),
        station=station,
        operator=str(batch.get("operator") or "") or "not recorded",
        profile=str(batch.get("profile") or run.get("profile") or ""),
        limits_name=run.get("limits_name"),
        limits_version=run.get("limits_version"),
        started_at=run.get("started_at"),
        ended_at=run.get("ended_at"),
        judged_at=run.get("judged_at"),
        verdict=run.get("verdict"),
        grade=run.get("grade"),
        tray=run.get("tray"),
        reason=run.get("reason"),
        thermal_method=run.get("thermal_method"),
        coefficients=_coefficients(run.get("thermal_by_method") or {}, run.get("thermal_method"), run.get("sfem"),
                                   checks),
        checks=checks,
        program_verify=run.get("program_verify"),
        verification=verification,
        fit_points=points,
        issued_at=(issued_at or datetime.now(timezone.utc)).isoformat(timespec="seconds"),
        revision=revision,
        certificate_id=certificate_id(station, run_id, revision),
        issuer=_issuer(certificate_config if certificate_config is not None else snapshot.get("certificate")),
        guard_sigma=guard,
        guard_sigma_stored=guard_stored,
        environment=_environment(segments, verification, snapshot),
        software_version=software_version,
        schema_version=batch.get("schema_version"),
    )


# ---- text of the certificate (pure) ------------------------------------------------------------
def _when(iso: str | None) -> str:
    """ISO time to the second, UTC (the stored times carry microseconds)."""
    if not iso:
        return "-"
    try:
        return datetime.fromisoformat(iso).astimezone(timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")
    except ValueError:
        return iso


def _num(v: Any, spec: str = ".4g") -> str:
    f = _f(v)
    return "-" if f is None else format(f, spec)


def _cfg(v: str) -> str:
    return v or NOT_CONFIGURED


def _value_u(value: float | None, u: float | None) -> str:
    """value ± U as a calibration certificate writes it (U with two significant digits)."""
    if value is None:
        return "n/a"
    v = f"{value:+.4g}"
    return f"{v} ± {u:.2g}" if u is not None else f"{v} (no uncertainty)"


def limits_text(low: Any, high: Any) -> str:
    lo, hi = _f(low), _f(high)
    if lo is not None and hi is not None:
        return f"= {lo:.4g}" if lo == hi else f"{lo:.4g} .. {hi:.4g}"
    if lo is not None:
        return f"≥ {lo:.4g}"
    if hi is not None:
        return f"≤ {hi:.4g}"
    return "present (no limit)"


def check_cells(c: dict, guard_sigma: float) -> tuple[str, ...]:
    """One check as its row: outcome, measurement, axis, value, unit, limit(s), 1-sigma, ±k sigma."""
    value = _f(c.get("value"))
    sigma = _f(c.get("sigma"))
    name = str(c.get("measurement") or "")
    unit = str(c.get("unit") or "") or ("1 = yes" if name in FLAG_CHECKS else "")
    return (str(c.get("outcome") or "-").upper(), name, str(c.get("axis") or "-"),
            "not measured" if value is None else f"{value:.4g}", unit or "-", limits_text(c.get("low"), c.get("high")),
            "-" if sigma is None else f"{sigma:.2g}", "-" if sigma is None else f"{guard_sigma * sigma:.2g}")


def model_statement() -> list[str]:
    """The thermal model the coefficients belong to, one short line each (no line is wrapped)."""
    return [
        f"{MODEL_EQUATION}    (martinez2022 eq. 1), Tref = {T_REF_C:g} °C",
        "Acc: the axis output in g at board temperature T in °C; Acc0: the axis output at Tref.",
        "TDB: thermal drift of the bias in mg/°C (enters the equation as 1e-3 g/°C).",
        "TDSF: thermal drift of the scale factor in ppm/°C (enters the equation as 1e-6 /°C); a positive TDSF "
        "is clamped to 0 by the method (not observable).",
        "The board compensates its output with the written TDB and TDSF by this equation.",
    ]


def uncertainty_statement(cert: Certificate) -> list[str]:
    return [
        f"Each coefficient is stated as value ± U, the expanded uncertainty U = k · u with coverage factor "
        f"k = {COVERAGE_K:g}, which for a normal distribution corresponds to a coverage probability of approximately "
        "95 %. u is the combined standard uncertainty the verdict judged with: the run's own budget (fit scatter, "
        "bias wander, temperature quantiser, MEMS lag; docs/verdicts.md \"Uncertainty budget\") combined in quadrature "
        "with the limits set's systematic term u_sys (the scale of the on-die temperature reading, an assumed value); "
        "where no check judged a coefficient, u is the run's own budget alone. The checks list 1σ = u and the "
        "guard-band half-width. In the station's coverage benchmark against simulated truth (LIS3DSH parts, "
        "benchmarks/coverage.py, docs/verdicts.md) 94-98 % of the TDB, TDSF and verified E errors lay within 2u "
        "(90-98 % over other seeds).",
    ]


def decision_rule_statement(cert: Certificate) -> list[str]:
    k = f"{cert.guard_sigma:g}"
    src = ("the limits set's guard_sigma" if cert.guard_sigma_stored
           else "the station default; this limits set is not in the batch's stored config")
    return [
        f"Guarded acceptance (station/decisions/verdicts.py; docs/verdicts.md): each measurement is judged with its interval "
        f"value ± k·σ, k = {k} ({src}), σ = sqrt(σ_measured² + u_sys²) (the 1σ column). "
        "PASS: the run ended done, every measurement the profile and the limits set require is present, and every "
        "interval lies inside its limits and outside any marginal band. MARGINAL: an interval crosses a limit, or "
        "reaches into a limit's marginal band: the data cannot tell good from bad. FAIL: an interval lies wholly "
        "outside a limit, or a part inside every limit meets no grade. ERROR: the run did not complete, its "
        "analysis failed or a required measurement is missing; never pass. A check without a stated σ is judged "
        f"on its value alone. With k = {k} a check whose true value lies at its limit passes with a probability "
        f"of at most {_false_accept_pct(cert.guard_sigma)} (one-sided, normal, σ as stated). The grade is the first "
        "grade whose extra limits every interval meets with the same guard band.",
    ]


def _false_accept_pct(k: float) -> str:
    return f"{50.0 * math.erfc(k / math.sqrt(2.0)):.2g} %"


def traceability_statement(cert: Certificate) -> list[str]:
    env = cert.environment
    if env.plate_thermometer:
        own = cert.issuer.reference_thermometer or "not stated in the config ([certificate] reference_thermometer)"
        plate = (f"The plate reference thermometer ({env.plate_thermometer}) guards the plate's over-temperature "
                 f"limit only: its readings enter no coefficient and are not stored with the run. Its own calibration: "
                 f"{own}.")
    else:
        plate = "No plate reference thermometer was configured for this batch."
    return [
        "Temperature: every temperature in the coefficients (T and T - Tref) is the DUT board's own temperature "
        "sensor (on the sensor die, read through the board's reported scale). This station does not calibrate it "
        "against a reference, so the coefficients are per board-reading degree and are NOT metrologically traceable "
        "to the SI kelvin; the board compensates with the same reading. Its scale error is the assumed systematic "
        "term u_sys, not a measured one. " + plate,
        "Acceleration: the reference is gravity. The fixture holds each axis at ±0.577 g (nominal, the body "
        "diagonal); local g is not measured and the fixture angles are not calibrated. TDB and TDSF are slopes of "
        "the DUT's own output against its own temperature reading, in the DUT's nominal sensitivity "
        "(1 mg = 1e-3 of the nominal 1 g); they depend on g only through its constancy during the run and are NOT "
        "traceable to an SI acceleration standard. Times: the station's clock, UTC.",
    ]


def environment_statement(cert: Certificate) -> list[str]:
    env = cert.environment
    if env.dut_temp_min_c is not None:
        dut = (f"DUT temperature (board sensor) over the {env.n_segments} stored stable segments: "
               f"{env.dut_temp_min_c:.1f} to {env.dut_temp_max_c:.1f} °C.")
    else:
        dut = "DUT temperature: not recorded (no stable segments stored)."
    if env.verify_temp_from_c is not None and env.verify_temp_to_c is not None:
        dut += (f" Verification heat (program and verify): {env.verify_temp_from_c:.1f} to "
                f"{env.verify_temp_to_c:.1f} °C.")
    plate = ("plate reference thermometer: readings not stored with the run, not recorded"
             if env.plate_thermometer else "plate temperature: no reference thermometer, not recorded")
    return [f"{dut} Ambient (room) temperature and humidity: not recorded by the station; {plate}. "
            "The plate is heated by the station's IR lamp during the run (the profile's steps)."]


def closing_statement(cert: Certificate) -> list[str]:
    return [
        "The results relate only to the item calibrated, as received and at the time of the calibration. This "
        "certificate shall not be reproduced except in full. It follows the reporting items of ISO/IEC 17025:2017 "
        "clause 7.8 and does not by itself claim an accreditation. Customer: not recorded by the station.",
    ]


# ---- layout (pure): rows of known height, split over pages --------------------------------------
PAGE_W_IN, PAGE_H_IN = 8.27, 11.69  # A4
LEFT_IN, RIGHT_IN = 0.6, 7.67
BODY_TOP_IN = 0.8  # below the running header
BODY_BOTTOM_IN = PAGE_H_IN - 0.75  # above the footer ("page x of y")
WRAP_CHARS = 104  # 8 pt DejaVu Sans over LEFT_IN..RIGHT_IN, with room to spare
FIELD_WRAP_CHARS = 80
ROW_HEIGHT_IN = {
    "title": 0.42, "subtitle": 0.22, "serial": 0.32, "verdict": 0.3, "heading": 0.32, "text": 0.158,
    "field": 0.165, "table_head": 0.2, "table_row": 0.155, "gap": 0.1, "plot": 3.1, "sign": 0.5,
}
CHECK_COLUMNS_IN = (0.6, 1.3, 3.25, 3.6, 4.45, 5.25, 6.45, 7.05)
CHECK_NAME_CHARS = 30  # of a measurement name in its column (the longest built-in one has 28)
COEF_COLUMNS_IN = (0.6, 1.55, 2.0, 3.75, 4.45, 5.2)
PV_COLUMNS_IN = (0.6, 1.2, 2.25, 3.9, 5.0, 6.65)


@dataclass(frozen=True)
class Row:
    """One line of the certificate. kind sets its height and style; `cells` its text (one per
    column of its table, else one); `tone` a colour (pass, marginal, fail, error); `table` the
    columns' x positions (inches); `cont` the rows to repeat above it when it begins a page (a
    table's heading and header); `keep` glues it to the next row (a heading never ends a page)."""

    kind: str
    cells: tuple[str, ...] = ()
    tone: str = ""
    table: tuple[float, ...] = ()
    cont: tuple["Row", ...] = ()
    keep: bool = False

    @property
    def height_in(self) -> float:
        return ROW_HEIGHT_IN[self.kind]


def _text_rows(paragraphs: Iterable[str], width: int = WRAP_CHARS) -> list[Row]:
    out: list[Row] = []
    for p in paragraphs:
        out += [Row("text", (line,)) for line in textwrap.wrap(p, width)] or [Row("text", ("",))]
    return out


def _field_rows(key: str, value: str) -> list[Row]:
    lines = textwrap.wrap(value, FIELD_WRAP_CHARS) or ["-"]
    return [Row("field", (key if i == 0 else "", line)) for i, line in enumerate(lines)]


def _section(heading: str, paragraphs: Iterable[str]) -> list[Row]:
    return [Row("gap"), Row("heading", (heading,), keep=True), *_text_rows(paragraphs)]


def _checks_heading(cert: Certificate) -> str:
    if not cert.checks:
        return "Checks against the limits"
    counts = cert.outcome_counts()
    parts = ", ".join(f"{counts[o]} {o}" for o in (*OUTCOME_ORDER, *sorted(set(counts) - set(OUTCOME_ORDER)))
                      if counts.get(o))
    return f"Checks against the limits: all {len(cert.checks)} checks of the verdict ({parts}), worst first"


def _pv_rows(cert: Certificate) -> list[Row]:
    """Program and verify: written, read back, compensation, and the verified drift error per axis
    with units (E in mg, E_FS in % of the 2000 mg span, eq. 12), U = k u where the sigma is stored."""
    pv = cert.program_verify or {}
    ver = cert.verification or {}
    rows = [Row("gap"), Row("heading", ("Program and verify (coefficients written to the board, then verified)",),
                            keep=True)]
    match = bool(pv.get("programmed") and pv.get("crc") and pv.get("crc") == pv.get("readback_crc"))
    rows += _text_rows([
        f"Programmed: {'yes' if pv.get('programmed') else 'no'}; CRC-32 written {pv.get('crc') or '-'}, read back "
        f"{pv.get('readback_crc') or '-'}: CRC readback match {'yes' if match else 'no'}; on-board compensation "
        f"{'on' if pv.get('comp_on') else 'off'}; tries {pv.get('attempts') or 0}"
        + (f"; error: {pv.get('error_kind')}: {pv.get('error')}" if pv.get("error_kind") or pv.get("error") else "")
        + ".",
        "Verification: " + {True: "passed", False: "failed", None: "not verified"}[pv.get("verified")]
        + ("" if not pv.get("flags") else " (" + "; ".join(str(f) for f in pv["flags"]) + ")")
        + (f"; operating range {_num(ver['range_c'][0], '.0f')} to {_num(ver['range_c'][1], '.0f')} °C"
           if isinstance(ver.get("range_c"), (list, tuple)) and len(ver["range_c"]) == 2 else "") + ".",
    ])
    written = pv.get("written") if isinstance(pv.get("written"), dict) else {}
    units = {"tdb_mg_per_c": ("TDB", "mg/°C"), "tdsf_ppm_per_c": ("TDSF", "ppm/°C")}
    parts = [f"{units[k][0]} " + ", ".join(f"{ax} {_num(v.get(ax), '+.4g')}" for ax in AXES) + f" {units[k][1]}"
             for k, v in written.items() if k in units and isinstance(v, dict)]
    if parts:  # what the board holds, when the program record names it
        rows += _text_rows(["Written to the board: " + "; ".join(parts) + "."])
    before = pv.get("e_before_mg") or ver.get("e_before_mg") or {}
    after = pv.get("e_after_mg") or ver.get("e_after_mg") or {}
    if any(_f(before.get(ax)) is not None or _f(after.get(ax)) is not None for ax in AXES):
        head = Row("table_head", ("axis", "E before (mg)", f"E after (mg) ± U, k={COVERAGE_K:g}", "E_FS before (%FS)",
                                  f"E_FS after (%FS) ± U, k={COVERAGE_K:g}", "axis rule"), table=PV_COLUMNS_IN)
        rows.append(head)
        sig_mg = ver.get("e_after_sigma_mg") or {}
        fs = ver.get("e_after_fs_pct") or {}
        sig_fs = ver.get("e_after_fs_sigma_pct") or {}
        axes = ver.get("axes") or {}
        for ax in AXES:
            b, a = _f(before.get(ax)), _f(after.get(ax))
            s_mg = _f(sig_mg.get(ax))
            check = next((c for c in cert.checks if c.get("measurement") == "verified_drift_error_fs_pct"
                          and c.get("axis") == ax), {})
            a_fs = _f(fs.get(ax))
            if a_fs is None:
                a_fs = _f(check.get("value"))
            if a_fs is None and a is not None:
                a_fs = a / FULL_SCALE_MG * 100.0
            s_fs = _f(sig_fs.get(ax))
            if s_fs is None:
                s_fs = _f(check.get("sigma"))
            passed = (axes.get(ax) or {}).get("passed")
            rows.append(Row("table_row", (
                ax, _num(b, ".3g"),
                "-" if a is None else (f"{a:.3g}" + (f" ± {COVERAGE_K * s_mg:.2g}" if s_mg is not None else "")),
                "-" if b is None else f"{b / FULL_SCALE_MG * 100.0:.3g}",
                "-" if a_fs is None else (f"{a_fs:.3g}" + (f" ± {COVERAGE_K * s_fs:.2g}" if s_fs is not None else "")),
                {True: "passed", False: "failed", None: "-"}[passed]),
                tone={True: "pass", False: "fail"}.get(passed, ""), table=PV_COLUMNS_IN))
    return rows


def _check_rows(cells: tuple[str, ...], tone: str, cont: tuple[Row, ...]) -> list[Row]:
    """One check: one row, or more when a (site-defined) measurement name is longer than its column,
    the name wrapped onto rows that stay on the check's page."""
    names = textwrap.wrap(cells[1], CHECK_NAME_CHARS) or [""]
    first = Row("table_row", (cells[0], names[0], *cells[2:]), tone=tone, table=CHECK_COLUMNS_IN, cont=cont,
                keep=len(names) > 1)
    more = [Row("table_row", ("", n), tone=tone, table=CHECK_COLUMNS_IN[:2], keep=i < len(names) - 2)
            for i, n in enumerate(names[1:])]
    return [first, *more]


def certificate_rows(cert: Certificate) -> list[Row]:
    """The whole certificate as rows, in reading order (see the module doc)."""
    iss = cert.issuer
    rows: list[Row] = [
        Row("title", ("Calibration certificate",)),
        Row("subtitle", (f"Certificate {cert.certificate_id}    issued {_when(cert.issued_at)}",)),
        Row("gap"),
        *_field_rows("Issued by", _cfg(iss.issuer)),
        *_field_rows("Address / place", _cfg(iss.address) + f" (station {cert.station})"),
        *_field_rows("Authorised by", _cfg(iss.authorised_by)),
        Row("gap"),
        Row("serial", (f"Serial {cert.serial}",)),
        Row("verdict", (f"Verdict {(cert.verdict or 'not judged').upper()}    grade {cert.grade or '-'}    "
                        f"tray {cert.tray or '-'}",), tone=cert.verdict or ""),
    ]
    if cert.verdict:
        rows += _text_rows([f"Statement of conformity: {cert.verdict.upper()} against limits set "
                            f"{cert.limits_name or '-'} version {cert.limits_version or '-'} under the decision rule "
                            f"below (guard band k = {cert.guard_sigma:g})."
                            + (f" Reason: {cert.reason}" if cert.reason else "")])
    rows.append(Row("gap"))
    ver = (f"verdict record revision {cert.revision}" if cert.revision else "no verdict record (not judged)")
    for k, v in (
        ("Item", f"{cert.sensor or '-'} accelerometer, serial {cert.serial}, firmware {cert.firmware}"),
        ("Station / operator", f"{cert.station} / {cert.operator}"),
        ("Method (profile)", f"{cert.profile or '-'}; coefficients by the {cert.thermal_method or '-'} fit "
                             "(martinez2022)" if cert.thermal_method else f"{cert.profile or '-'}"),
        ("Limits", f"{cert.limits_name or '-'} version {cert.limits_version or '-'}"),
        ("Batch / run / attempt", f"{cert.batch_id} / {cert.run_id} / {cert.attempt or '-'}; {ver}"),
        ("Measured", f"{_when(cert.started_at)} to {_when(cert.ended_at)}"),
        ("Judged / issued", f"{_when(cert.judged_at)} / {_when(cert.issued_at)}"),
        ("Software", f"thermal-cal-station {cert.software_version or 'unknown'} (issued this certificate); the version "
                     f"that measured is not stored with the run (database schema {cert.schema_version or '-'})"),
    ):
        rows += _field_rows(k, v)
    if cert.coefficients:
        head = Row("table_head", ("coefficient", "axis", f"value ± U (k={COVERAGE_K:g})", "unit", "u (1σ)", "note"),
                   table=COEF_COLUMNS_IN)
        heading = Row("heading", (f"Results: coefficients ({cert.thermal_method or 'stored'} fit; Tref {T_REF_C:g} °C; "
                                  f"U = k·u, k = {COVERAGE_K:g}, ≈95 %)",), keep=True)
        cont = (Row("heading", ("Results: coefficients (continued)",), keep=True), head)
        rows += [Row("gap"), heading, Row("table_head", head.cells, table=COEF_COLUMNS_IN, keep=True)]
        for c in cert.coefficients:
            rows.append(Row("table_row", (c.name, c.axis, _value_u(c.value, c.expanded_u), c.unit,
                                          "-" if c.u is None else f"{c.u:.2g}", c.note),
                            table=COEF_COLUMNS_IN, cont=cont))
    else:
        rows += [Row("gap"), Row("heading", ("Results: coefficients",), keep=True),
                 *_text_rows(["No coefficients stored for this run."])]
    if cert.program_verify or cert.verification:
        rows += _pv_rows(cert)
    head = Row("table_head", ("outcome", "measurement", "axis", "value", "unit", "limit(s)", "1σ",
                              f"±{cert.guard_sigma:g}σ"), table=CHECK_COLUMNS_IN)
    cont = (Row("heading", ("Checks against the limits (continued)",), keep=True), head)
    rows += [Row("gap"), Row("heading", (_checks_heading(cert),), keep=True)]
    if cert.checks:
        rows.append(Row("table_head", head.cells, table=CHECK_COLUMNS_IN, keep=True))
        for c in cert.checks:
            rows += _check_rows(check_cells(c, cert.guard_sigma), str(c.get("outcome") or ""), cont)
    else:
        rows += _text_rows(["No checks: " + (f"the run was not judged against limits ({cert.reason})." if cert.reason
                                             else "the run was not judged against limits.")])
    rows += _section("Model", model_statement())
    rows += _section("Measurement uncertainty", uncertainty_statement(cert))
    rows += _section("Decision rule", decision_rule_statement(cert))
    rows += _section("Traceability", traceability_statement(cert))
    rows += _section("Environmental conditions", environment_statement(cert))
    if cert.fit_points or any(c.name in ("TDB", "TDSF") for c in cert.coefficients):
        rows += [Row("gap"), Row("heading", ("Fit: segment means against temperature with the thermal model "
                                             "(martinez2022 eq. 1)",), keep=True), Row("plot")]
    rows += _section("Validity", closing_statement(cert))
    rows += [Row("gap"), Row("sign", (f"Authorised by: {_cfg(iss.authorised_by)}", "Signature / date: ____________"))]
    return rows


def paginate(rows: list[Row], usable_in: float = BODY_BOTTOM_IN - BODY_TOP_IN) -> list[list[Row]]:
    """Rows onto pages by height: a page takes rows while they fit; a row that does not fit starts
    the next page (with its `cont` rows above it: a table's heading and header again); a `keep`
    row goes with the one after it; a gap never starts a page. Nothing is dropped: a row taller
    than a page still gets a page of its own."""
    pages: list[list[Row]] = [[]]
    used = 0.0
    i = 0
    while i < len(rows):
        j = i  # the run of rows that must stay together: keep rows and the row they lead to
        while rows[j].keep and j + 1 < len(rows):
            j += 1
        group = rows[i:j + 1]
        i = j + 1
        if pages[-1] and used + sum(r.height_in for r in group) > usable_in + 1e-9:
            pages.append([])
            used = 0.0
        if not pages[-1]:  # the group begins a page: no gap above it, its table's header again
            while group and group[0].kind == "gap":
                group = group[1:]
            if group and group[0].cont:
                group = [*group[0].cont, *group]
        pages[-1].extend(group)
        used += sum(r.height_in for r in group)
    return pages


def layout(cert: Certificate) -> list[list[Row]]:
    """The certificate's pages (pure): what render_pdf draws, page by page."""
    return paginate(certificate_rows(cert))


# ---- reading the records -----------------------------------------------------------------------
def software_version() -> str:
    """The installed station package's version (the software that issues the certificate)."""
    try:
        from importlib.metadata import version

        return version("thermal-cal-station")
    except Exception:  # noqa: BLE001 - a source tree that is not installed: say so, guess nothing
        return ""


def certificate_for(db: Any, serial: str, issued_at: datetime | None = None,
                    certificate_config: dict | None = None) -> Certificate | None:
    """The certificate of a serial's result run (its latest valid attempt); None for an unknown
    serial. Raises LookupError for a known serial without any result yet. certificate_config: a
    `[certificate]` section to print instead of the one stored with the run's batch."""
    from sqlalchemy import select

    from db import repository as repo
    from db.models import ProgramVerifyRow

    dut = repo.dut_by_serial(db, serial)
    if dut is None:
        return None
    run_id = dut.get("result_run_id")
    if run_id is None:
        raise LookupError(f"DUT {serial} has no stored result yet: no certificate")
    run = repo.run_detail(db, int(run_id)) or {}
    batch = repo.batch_detail(db, int(run["batch_id"])) or {}
    revision = None
    with db.session() as s:
        if run.get("result_seq") is not None:
            revision = int(s.scalar(select(repo.revision_of(int(run_id), int(run["result_seq"])))) or 0) or None
        verification = s.scalar(select(ProgramVerifyRow.verification).where(ProgramVerifyRow.run_id == int(run_id)))
    return build_certificate(run, batch, repo.segments_of_run(db, int(run_id)) or [], issued_at, revision=revision,
                             verification=verification if isinstance(verification, dict) else None,
                             certificate_config=certificate_config, software_version=software_version())


# ---- rendering ---------------------------------------------------------------------------------
_TONE = {"pass": "green", "marginal": "darkorange", "fail": "red", "error": "red"}
_STYLE = {  # kind: (font size pt, weight)
    "title": (16, "bold"), "subtitle": (9, "normal"), "serial": (13, "bold"), "verdict": (12, "bold"),
    "heading": (10, "bold"), "text": (8, "normal"), "field": (8, "normal"), "table_head": (7.5, "bold"),
    "table_row": (7.5, "normal"), "sign": (9, "normal"),
}


def _fit_axes(ax_plot: Any, cert: Certificate, k: int) -> None:
    """Axis k: segment means (mg, each orientation relative to its level at T_ref) and the model."""
    import numpy as np

    axis = AXES[k]
    tdb = cert.coefficient("TDB", axis)
    tdsf = cert.coefficient("TDSF", axis)
    b_mg = (tdb.value if tdb and tdb.value is not None else 0.0)
    s_ppm = (tdsf.value if tdsf and tdsf.value is not None else 0.0)
    groups: dict[int, list[FitPoint]] = {}
    for p in cert.fit_points:
        groups.setdefault(p.orientation, []).append(p)
    colors = ["tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown"]
    for i, (orient, pts) in enumerate(sorted(groups.items())):
        t = np.array([p.temp_c for p in pts])
        a = np.array([p.acc_g[k] for p in pts])
        slope_g = b_mg * 1e-3 + np.mean(a) * s_ppm * 1e-6  # d(acc)/dT of eq. 1 at this orientation
        a0 = float(np.mean(a - slope_g * (t - T_REF_C)))  # the level at T_ref that fits best
        c = colors[i % len(colors)]
        ax_plot.plot(t, (a - a0) * 1e3, "o", ms=3, color=c, label=f"orientation {orient}")
        tt = np.linspace(min(t.min(), T_REF_C), max(t.max(), T_REF_C + 1), 20)
        model = a0 * (1 + s_ppm * 1e-6 * (tt - T_REF_C)) + b_mg * 1e-3 * (tt - T_REF_C)
        ax_plot.plot(tt, (model - a0) * 1e3, "-", lw=1, color=c)
    ax_plot.set_title(f"{axis}", fontsize=8)
    ax_plot.set_xlabel("temperature (°C)", fontsize=7)
    if k == 0:
        ax_plot.set_ylabel("Δacc (mg)", fontsize=7)
    ax_plot.tick_params(labelsize=6)
    ax_plot.grid(alpha=0.3)
    if groups and k == 0:
        ax_plot.legend(fontsize=6, loc="best")
    if not groups:
        ax_plot.text(0.5, 0.5, "no segments stored", ha="center", va="center", fontsize=7, transform=ax_plot.transAxes)


def _draw_page(fig: Any, cert: Certificate, rows: list[Row], page_no: int, n_pages: int) -> None:
    def put(x_in: float, y_in: float, text: str, size: float, weight: str = "normal", color: str = "black",
            ha: str = "left") -> None:
        fig.text(x_in / PAGE_W_IN, 1.0 - y_in / PAGE_H_IN, text, fontsize=size, weight=weight, color=color,
                 va="top", ha=ha, family="DejaVu Sans", parse_math=False)

    put(LEFT_IN, 0.4, f"Calibration certificate {cert.certificate_id} · serial {cert.serial}", 7, color="dimgray")
    put(RIGHT_IN, 0.4, _cfg(cert.issuer.issuer), 7, color="dimgray", ha="right")
    put(LEFT_IN, PAGE_H_IN - 0.55, f"Certificate {cert.certificate_id}", 7.5, color="dimgray")
    put(RIGHT_IN, PAGE_H_IN - 0.55, f"page {page_no} of {n_pages}", 7.5, ha="right")
    y = BODY_TOP_IN
    for r in rows:
        size, weight = _STYLE.get(r.kind, (8, "normal"))
        if r.kind == "plot":
            top, h = y + 0.1, r.height_in - 0.55
            for k in range(3):
                ax_plot = fig.add_axes(((LEFT_IN + 0.35 + k * 2.35) / PAGE_W_IN, 1.0 - (top + h) / PAGE_H_IN,
                                        1.9 / PAGE_W_IN, h / PAGE_H_IN))
                _fit_axes(ax_plot, cert, k)
        elif r.kind == "field":
            put(LEFT_IN, y, r.cells[0], size, color="dimgray")
            put(2.3, y, r.cells[1], size)
        elif r.kind == "sign":
            put(LEFT_IN, y + 0.15, r.cells[0], size)
            put(4.6, y + 0.15, r.cells[1], size)
        elif r.table:
            color = _TONE.get(r.tone, "black")
            for j, (x, text) in enumerate(zip(r.table, r.cells)):
                put(x, y, text, size, weight="bold" if (j == 0 and r.tone in ("fail", "error")) else weight,
                    color=color if j == 0 or r.tone in ("fail", "error") else "black")
            if r.kind == "table_head":
                fig.add_artist(_rule(fig, y + r.height_in - 0.04))
        elif r.cells:
            put(LEFT_IN, y + (0.06 if r.kind == "heading" else 0.0), r.cells[0], size, weight,
                color=_TONE.get(r.tone, "black") if r.kind == "verdict" else "black")
        y += r.height_in


def _rule(fig: Any, y_in: float) -> Any:
    from matplotlib.lines import Line2D

    y = 1.0 - y_in / PAGE_H_IN
    return Line2D([LEFT_IN / PAGE_W_IN, RIGHT_IN / PAGE_W_IN], [y, y], lw=0.4, color="gray",
                  transform=fig.transFigure)


def render_pdf(cert: Certificate) -> bytes:
    """The certificate as a PDF of as many A4 pages as `layout(cert)` needs."""
    from matplotlib.backends.backend_pdf import FigureCanvasPdf, PdfPages
    from matplotlib.figure import Figure

    pages = layout(cert)
    buf = io.BytesIO()
    with _LOCK:
        with PdfPages(buf, metadata={"Title": f"Calibration certificate {cert.serial} ({cert.certificate_id})",
                                     "Creator": "thermal calibration station"}) as pdf:
            for n, rows in enumerate(pages, start=1):
                fig = Figure(figsize=(PAGE_W_IN, PAGE_H_IN))
                FigureCanvasPdf(fig)
                _draw_page(fig, cert, rows, n, len(pages))
                pdf.savefig(fig)
    return buf.getvalue()


__all__ = ["Certificate", "Coefficient", "Environment", "FitPoint", "Issuer", "Row", "build_certificate",
           "certificate_for", "certificate_rows", "layout", "ordered_checks", "paginate", "render_pdf",
           "COVERAGE_K", "MODEL_EQUATION"]
