"""Calibration certificate of one DUT: what was measured on which station, by
whom, with which firmware, profile and limits version; the coefficients with their expanded
uncertainty; EVERY check the verdict used (failing first); program-and-verify when done; and the
statements ISO/IEC 17025:2017 clause 7.8 asks of a calibration certificate: unique id and "page x
of y", issuer and authorising person, the model equation, the uncertainty statement (U = k u,
k = 2), the decision rule behind the verdict, traceability and environmental conditions.

Three layers, as elsewhere in the station, one module each:
- this module, the pure core: `build_certificate(...)` takes stored rows (plain dicts, as
  db.repository gives them) and gives a typed `Certificate`. No database, no files, no matplotlib;
  a unit test gives it dicts. `certificate_for(db, serial)` is its database adapter: it reads the
  rows (the DUT's latest valid attempt, the same run `GET /api/duts/{serial}` reports).
- certificate_layout.py, the pure layout: the statements, `certificate_rows(cert)` and
  `paginate(rows)`, the certificate as rows of known height split over A4 pages.
- certificate_pdf.py, the drawing: `render_pdf(cert)` with matplotlib's PDF backend.

Who issues the certificate (`[certificate]` in the station config: issuer, address, authorised_by,
reference_thermometer) is read from the config snapshot stored with the run's batch: the same
record always prints the same certificate, and a station that never configured it prints "not
configured" instead of a made-up name. The CLI may pass a config's section instead.
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from typing import Any, Iterable

from contracts.json_safe import finite_or_none as _f
from contracts.types import AXES
from station.decisions.judging import RANK
from station.decisions.measurements import TDB, TDSF
from station.records.certificate_sfem import sfem_coefficients, sfem_lines

COVERAGE_K = 2.0  # coverage factor of the expanded uncertainty U = k u (about 95 % for a normal law)
DEFAULT_GUARD_SIGMA = 2.0  # spec_limits.ProductSpec.guard_sigma's default, when the stored config lacks the set
# worst first: a reader of page 1 sees what failed (the rank of station/decisions/verdicts.py)
OUTCOME_ORDER = tuple(sorted(RANK, key=RANK.__getitem__, reverse=True))  # error, fail, marginal, pass


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
    # traceability (contracts/trace.py): '' when the batch was started without them
    work_order: str = ""
    part_number: str = ""
    part_revision: str = ""
    lot: str = ""
    label_serial: str = ""
    issuer: Issuer = field(default_factory=Issuer)
    guard_sigma: float = DEFAULT_GUARD_SIGMA
    guard_sigma_stored: bool = False  # False: the limits set is not in the stored config (default used)
    environment: Environment = field(default_factory=Environment)
    software_version: str = ""  # the issuing station software
    # what measured the run, stored with it (dut_run, migration 0009); None: not stored (older run)
    measured_software_version: str | None = None
    holder: str | None = None  # 'fixture' (the motorized fixture turned the plate) or 'operator' (a person)
    schema_version: str | None = None  # the database schema the run was stored with
    sfem_lines: list[str] = field(default_factory=list)  # the SFEM section (certificate_sfem.sfem_lines)

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
        out.append(Coefficient(TDB.label, ax, _f(a.get(TDB.name)), _f(a.get(TDB.sigma_key)), TDB.shown_unit,
                               preferred or "", u_combined=_check_sigma(checks, TDB.name, ax)))
        out.append(Coefficient(TDSF.label, ax, _f(a.get(TDSF.name)), _f(a.get(TDSF.sigma_key)), TDSF.shown_unit,
                               preferred or "", "clamped to 0 (not observable)" if a.get("tdsf_clamped") else "",
                               u_combined=_check_sigma(checks, TDSF.name, ax)))
    # SFEM: the step nearest Tref and the thermal model's drift (station/records/certificate_sfem.py)
    for name, ax, value, sigma, unit, note, check, k in sfem_coefficients(sfem):
        u = None if check is None else _check_sigma(checks, check, ax)
        out.append(Coefficient(name, ax, value, sigma, unit, "sfem", note, u_combined=None if u is None else u * k))
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
        firmware=str(run.get("firmware_version") or identity.get("fw") or identity.get("firmware") or "") or "not reported",
        run_id=run_id,
        batch_id=int(run.get("batch_id") or 0),
        attempt=run.get("attempt"),
        station=station,
        operator=str(batch.get("operator") or "") or "not recorded",
        profile=str(batch.get("profile") or run.get("profile") or ""),
        work_order=str(batch.get("work_order") or run.get("work_order") or ""),
        part_number=str(batch.get("part_number") or run.get("part_number") or ""),
        part_revision=str(batch.get("part_revision") or run.get("part_revision") or ""),
        lot=str(batch.get("lot") or run.get("lot") or ""),
        label_serial=str(run.get("label_serial") or ""),
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
        measured_software_version=run.get("software_version") or None,
        holder=run.get("holder") or None,
        schema_version=batch.get("schema_version"),
        sfem_lines=sfem_lines(run.get("sfem")),
    )


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


__all__ = ["Certificate", "Coefficient", "Environment", "FitPoint", "Issuer", "build_certificate", "certificate_for",
           "certificate_id", "ordered_checks", "software_version", "COVERAGE_K", "DEFAULT_GUARD_SIGMA",
           "OUTCOME_ORDER"]
