"""Calibration certificate of one DUT (issue 13): what was measured on which station, by whom, with
which firmware, profile and limits version, the coefficients with their uncertainties and units,
the verdict and grade, and a plot of the fit.

Two layers, as elsewhere in the station:
- `build_certificate(...)` is the pure core: stored rows (plain dicts, as db.repository gives them)
  in, a typed `Certificate` out. No database, no files, no matplotlib; a unit test gives it dicts.
- `certificate_for(db, serial)` reads those rows (the DUT's latest valid attempt, the same run
  `GET /api/duts/{serial}` reports) and `render_pdf(cert)` draws the certificate with matplotlib's
  PDF backend (object API, no pyplot state, so the web's thread pool may call it).

The fit plot shows, per axis, the stable segments' mean acceleration against temperature (each
orientation relative to its own level at T_ref) with the thermal model's line through them
(martinez2022 eq. 1: Acc = Acc0 (1 + TDSF dT) + TDB dT): the reader sees the points the
coefficients came from.
"""

from __future__ import annotations

import io
import threading
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any

from station.types import AXES, T_REF_C

_LOCK = threading.Lock()  # matplotlib's text layout is not fully thread safe (as web/plots.py)


@dataclass(frozen=True)
class Coefficient:
    """One calibrated coefficient: value ± 1 sigma (None when the method gives none), unit."""

    name: str  # "TDB", "TDSF", "SFEM bias", ...
    axis: str
    value: float | None
    sigma: float | None
    unit: str
    method: str = ""
    note: str = ""  # e.g. "clamped" (TDSF held at 0: not observable in this run)


@dataclass(frozen=True)
class FitPoint:
    """One stable segment for the fit plot: temperature and mean acceleration per axis (g)."""

    temp_c: float
    acc_g: tuple[float, float, float]
    orientation: int


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
    checks: list[dict] = field(default_factory=list)  # the verdict's checks (station/verdicts.py)
    program_verify: dict | None = None
    fit_points: list[FitPoint] = field(default_factory=list)
    issued_at: str = ""

    def coefficient(self, name: str, axis: str) -> Coefficient | None:
        return next((c for c in self.coefficients if c.name == name and c.axis == axis), None)

    def to_json(self) -> dict:
        from dataclasses import asdict

        return asdict(self)


def _f(v: Any) -> float | None:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if f == f and abs(f) != float("inf") else None


def _coefficients(thermal_by_method: dict, preferred: str | None, sfem: dict | None) -> list[Coefficient]:
    out: list[Coefficient] = []
    res = (thermal_by_method or {}).get(preferred or "") or {}
    for ax in AXES:
        a = res.get(ax) or {}
        if not a:
            continue
        out.append(Coefficient("TDB", ax, _f(a.get("tdb_mg_per_c")), _f(a.get("tdb_sigma_mg_per_c")), "mg/°C",
                               preferred or ""))
        out.append(Coefficient("TDSF", ax, _f(a.get("tdsf_ppm_per_c")), _f(a.get("tdsf_sigma_ppm_per_c")), "ppm/°C",
                               preferred or "", "clamped to 0 (not observable)" if a.get("tdsf_clamped") else ""))
    if isinstance(sfem, dict):
        fit = sfem
        steps = sfem.get("steps")
        if isinstance(steps, list) and steps:
            fit = steps[0] or {}  # the first temperature step (the polynomials are in the JSON record)
        b = fit.get("b") or fit.get("bias_g")
        if isinstance(b, (list, tuple)) and len(b) == 3:
            for ax, v in zip(AXES, b):
                out.append(Coefficient("SFEM bias", ax, None if _f(v) is None else _f(v) * 1e3, None, "mg", "sfem"))
    return out


def build_certificate(run: dict, batch: dict, segments: list[dict], issued_at: datetime | None = None) -> Certificate:
    """The certificate of one run. run: db.repository.run_detail (with thermal results, verdict
    detail, program_verify); batch: db.repository.batch_detail (station, operator, profile);
    segments: db.repository.segments_of_run."""
    identity = run.get("identity") or {}
    detail = run.get("verdict_detail") or {}
    checks = [c for c in (detail.get("checks") or []) if isinstance(c, dict)]
    points = []
    for g in segments or []:
        acc = g.get("acc_mean_g")
        t = _f(g.get("temp_mean_c"))
        if isinstance(acc, (list, tuple)) and len(acc) == 3 and t is not None and all(_f(v) is not None for v in acc):
            points.append(FitPoint(t, (float(acc[0]), float(acc[1]), float(acc[2])), int(g.get("orientation") or 0)))
    return Certificate(
        serial=str(run.get("serial") or identity.get("serial") or ""),
        sensor=str(identity.get("sensor") or run.get("sensor") or ""),
        firmware=str(identity.get("fw") or identity.get("firmware") or "") or "not reported",
        run_id=int(run["id"]),
        batch_id=int(run.get("batch_id") or 0),
        attempt=run.get("attempt"),
        station=str(batch.get("station") or run.get("station") or "") or "unnamed",
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
        coefficients=_coefficients(run.get("thermal_by_method") or {}, run.get("thermal_method"), run.get("sfem")),
        checks=checks,
        program_verify=run.get("program_verify"),
        fit_points=points,
        issued_at=(issued_at or datetime.now(timezone.utc)).isoformat(timespec="seconds"),
    )


def certificate_for(db: Any, serial: str, issued_at: datetime | None = None) -> Certificate | None:
    """The certificate of a serial's result run (its latest valid attempt); None for an unknown
    serial. Raises LookupError for a known serial without any result yet."""
    from db import repository as repo

    dut = repo.dut_by_serial(db, serial)
    if dut is None:
        return None
    run_id = dut.get("result_run_id")
    if run_id is None:
        raise LookupError(f"DUT {serial} has no stored result yet: no certificate")
    run = repo.run_detail(db, int(run_id)) or {}
    batch = repo.batch_detail(db, int(run["batch_id"])) or {}
    return build_certificate(run, batch, repo.segments_of_run(db, int(run_id)) or [], issued_at)


# ---- rendering ---------------------------------------------------------------------------------
def _when(iso: str | None) -> str:
    """ISO time to the second, UTC (the stored times carry microseconds)."""
    if not iso:
        return "-"
    try:
        return datetime.fromisoformat(iso).astimezone(timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")
    except ValueError:
        return iso


def _fmt(c: Coefficient) -> str:
    if c.value is None:
        return "n/a"
    v = f"{c.value:+.4g}"
    return f"{v} ± {c.sigma:.2g}" if c.sigma is not None else v


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


def render_pdf(cert: Certificate) -> bytes:
    """One A4 page: header, identity and provenance, coefficients table, checks, fit plot."""
    from matplotlib.backends.backend_pdf import FigureCanvasPdf
    from matplotlib.figure import Figure

    with _LOCK:
        fig = Figure(figsize=(8.27, 11.69))
        FigureCanvasPdf(fig)
        y = 0.965

        def line(text: str, size: float = 9, weight: str = "normal", x: float = 0.07, dy: float = 0.019,
                 color: str = "black") -> None:
            nonlocal y
            fig.text(x, y, text, fontsize=size, weight=weight, color=color, va="top", family="DejaVu Sans")
            y -= dy

        line("Calibration certificate", 16, "bold", dy=0.03)
        line(f"Serial {cert.serial}", 12, "bold", dy=0.026)
        verdict_color = {"pass": "green", "marginal": "darkorange", "fail": "red", "error": "red"}.get(cert.verdict or "", "black")
        line(f"Verdict {(cert.verdict or 'not judged').upper()}    grade {cert.grade or '-'}    tray {cert.tray or '-'}",
             12, "bold", color=verdict_color, dy=0.024)
        if cert.reason:
            line(f"Reason: {cert.reason}"[:130], 8)
        y -= 0.006
        rows = [
            ("Sensor", cert.sensor or "-"), ("Firmware", cert.firmware),
            ("Station", cert.station), ("Operator", cert.operator),
            ("Profile", cert.profile or "-"),
            ("Limits", f"{cert.limits_name or '-'} version {cert.limits_version or '-'}"),
            ("Batch / run / attempt", f"{cert.batch_id} / {cert.run_id} / {cert.attempt or '-'}"),
            ("Measured", f"{_when(cert.started_at)} to {_when(cert.ended_at)}"),
            ("Judged", _when(cert.judged_at)), ("Issued", _when(cert.issued_at)),
        ]
        for k, v in rows:
            fig.text(0.07, y, k, fontsize=8, va="top", color="dimgray")
            fig.text(0.30, y, str(v), fontsize=8, va="top")
            y -= 0.016
        y -= 0.008
        line(f"Coefficients ({cert.thermal_method or 'no thermal result'}; ± one standard uncertainty; "
             f"T_ref {T_REF_C:g} °C)", 10, "bold", dy=0.021)
        fig.text(0.07, y, "coefficient", fontsize=8, va="top", weight="bold")
        fig.text(0.27, y, "axis", fontsize=8, va="top", weight="bold")
        fig.text(0.35, y, "value", fontsize=8, va="top", weight="bold")
        fig.text(0.57, y, "unit", fontsize=8, va="top", weight="bold")
        fig.text(0.68, y, "note", fontsize=8, va="top", weight="bold")
        y -= 0.016
        for c in cert.coefficients:
            fig.text(0.07, y, c.name, fontsize=8, va="top")
            fig.text(0.27, y, c.axis, fontsize=8, va="top")
            fig.text(0.35, y, _fmt(c), fontsize=8, va="top")
            fig.text(0.57, y, c.unit, fontsize=8, va="top")
            fig.text(0.68, y, c.note, fontsize=7, va="top")
            y -= 0.015
        if not cert.coefficients:
            line("no coefficients stored", 8)
        pv = cert.program_verify
        if pv:
            y -= 0.006
            e_after = pv.get("e_after_mg") or {}
            verified = {True: "verified", False: "verification failed", None: "not verified"}[pv.get("verified")]
            line(f"Programmed: {'yes' if pv.get('programmed') else 'no'} (CRC {pv.get('crc') or '-'}, read back "
                 f"{pv.get('readback_crc') or '-'}), {verified}; E after (mg): "
                 + ", ".join(f"{ax} {e_after.get(ax):.3g}" for ax in AXES if e_after.get(ax) is not None), 8)
        if cert.checks:
            y -= 0.006
            line("Checks against the limits", 10, "bold", dy=0.02)
            for c in cert.checks[:14]:
                value = _f(c.get("value"))
                lo, hi = c.get("low"), c.get("high")
                text = (f"{c.get('measurement', '')} {c.get('axis') or ''}: "
                        f"{'n/a' if value is None else f'{value:.4g}'} {c.get('unit') or ''} "
                        f"(limits {lo if lo is not None else '-'} .. "
                        f"{hi if hi is not None else '-'}) {c.get('outcome', '')}")
                line(text[:120], 7.5, dy=0.015)
        top = max(0.08, min(y - 0.03, 0.38))
        h = top - 0.07
        for k in range(3):
            ax_plot = fig.add_axes((0.08 + k * 0.3, 0.07, 0.25, h - 0.03))
            _fit_axes(ax_plot, cert, k)
        fig.text(0.07, top, "Fit: segment means against temperature with the thermal model (martinez2022 eq. 1)",
                 fontsize=9, weight="bold", va="top")
        buf = io.BytesIO()
        fig.savefig(buf, format="pdf", metadata={"Title": f"Calibration certificate {cert.serial}",
                                                 "Creator": "thermal calibration station"})
        return buf.getvalue()


__all__ = ["Certificate", "Coefficient", "FitPoint", "build_certificate", "certificate_for", "render_pdf"]
