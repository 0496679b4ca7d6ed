"""The calibration certificate's words and where they go on the page: the statements (model,
uncertainty, decision rule, traceability, environment, validity), the certificate as rows of known
height (inches) in reading order, and their split over A4 pages.

Why a module of its own: this is the part a reader checks against ISO/IEC 17025 clause 7.8 and the
part that decides pagination, and both can be tested without drawing anything. It is pure (a
`Certificate` from station/records/certificate.py in, rows out; no database, no matplotlib), so
the number of pages is known before station/records/certificate_pdf.py draws them and every page
can say "page x of y". A page holds what its height holds, a table that goes on repeats its
header, and nothing is ever cut off.
"""

from __future__ import annotations

import math
import textwrap
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any, Iterable

from contracts.positions import FACING_MAX_ANGLE_DEG
from contracts.types import AXES, T_REF_C
from station.decisions.measurements import FLAG_UNIT_WORDS, TDB, TDSF, VERIFIED_DRIFT_ERROR_FS, is_flag
from station.records.certificate import COVERAGE_K, OUTCOME_ORDER, Certificate, _f
from station.science.thermal_model import FULL_SCALE_MG

NOT_CONFIGURED = "not configured"
# martinez2022 eq. 1 as the station implements it (station/science/thermal_model.py: apply_drift)
MODEL_EQUATION = "Acc(T) = Acc0 · (1 + TDSF · (T - Tref)) + TDB · (T - Tref)"


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
    unit = str(c.get("unit") or "") or (FLAG_UNIT_WORDS if is_flag(name) else "")  # a flag: 1 = yes, 0 = no
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
        "Acceleration: the reference is gravity, at the profile's nominal positions (P and N: ±0.577 g on each axis, "
        f"the body diagonal). {holder_statement(cert)} Local g is not measured. TDB and TDSF are slopes of "
        "the DUT's own output against its own temperature reading, in the DUT's nominal sensitivity "
        "(1 mg = 1e-3 of the nominal 1 g); they depend on g only through its constancy during the run and are NOT "
        "traceable to an SI acceleration standard. Times: the station's clock, UTC.",
    ]


def holder_statement(cert: Certificate) -> str:
    """What held the part while its positions were taken, as stored with the run (dut_run.holder)."""
    if cert.holder == "fixture":
        return "The station's motorized fixture turned the plate to each position; its angles are not calibrated."
    if cert.holder == "operator":
        return ("A person turned the plate to each position by hand (no fixture): the station took a sample at a "
                "position only while the DUT's own gravity reading pointed within "
                f"{FACING_MAX_ANGLE_DEG:g}° of it, so each angle is as the person set it, not calibrated.")
    return "What turned the plate (a fixture or a person) is not stored with this run; the angles are not calibrated."


def holder_words(cert: Certificate) -> str:
    return {"fixture": "the station's motorized fixture", "operator": "a person, by hand (no fixture)"}.get(
        cert.holder or "", "not stored with this run")


def software_words(cert: Certificate) -> str:
    """Which software measured the run (stored with it) and which issued this certificate."""
    issued = (f"thermal-cal-station {cert.software_version or 'unknown'} issued this certificate "
              f"(database schema {cert.schema_version or '-'})")
    if cert.measured_software_version:
        return f"thermal-cal-station {cert.measured_software_version} measured this run; {issued}"
    return f"{issued}; the version that measured is not stored with this run"


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
    units = {d.name: (d.label, d.shown_unit) for d in (TDB, TDSF)}
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
            check = next((c for c in cert.checks if c.get("measurement") == VERIFIED_DRIFT_ERROR_FS.name
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
        ("Part / revision", f"{cert.part_number or 'not recorded'} / {cert.part_revision or '-'}"),
        ("Work order / lot", f"{cert.work_order or 'not recorded'} / {cert.lot or 'not recorded'}"),
        ("Label serial", cert.label_serial or "not scanned"),
        ("Station / operator", f"{cert.station} / {cert.operator}"),
        ("Method (profile)", f"{cert.profile or '-'}; coefficients by the {cert.thermal_method or '-'} fit "
                             "(martinez2022)" if cert.thermal_method else f"{cert.profile or '-'}"),
        ("Limits", f"{cert.limits_name or '-'} version {cert.limits_version or '-'}"),
        ("Batch / run / attempt", f"{cert.batch_id} / {cert.run_id} / {cert.attempt or '-'}; {ver}"),
        ("Measured", f"{_when(cert.started_at)} to {_when(cert.ended_at)}"),
        ("Judged / issued", f"{_when(cert.judged_at)} / {_when(cert.issued_at)}"),
        ("Software", software_words(cert)),
        ("Plate turned by", holder_words(cert)),
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
    if cert.sfem_lines:  # station/records/certificate_sfem.py
        rows += _section("SFEM (sensors2023): step judged, thermal model, model check", cert.sfem_lines)
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


__all__ = ["Row", "certificate_rows", "check_cells", "layout", "limits_text", "paginate", "MODEL_EQUATION",
           "NOT_CONFIGURED", "BODY_BOTTOM_IN", "BODY_TOP_IN", "CHECK_COLUMNS_IN", "ROW_HEIGHT_IN"]
