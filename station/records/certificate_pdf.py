"""The calibration certificate as a PDF: the pages of station/records/certificate_layout.py drawn
with matplotlib's PDF backend (object API and PdfPages, no pyplot state, so the web's thread pool
may call it; a lock around the drawing, as matplotlib's text layout is not fully thread safe).

Why a module of its own: it is the only certificate module that imports matplotlib, so the core
(station/records/certificate.py) and the layout stay pure and light, testable without a plotting
library, and the drawing can change (or another backend be added) without touching what the
certificate says.

The fit plot shows, per axis, the stable segments' mean acceleration against temperature (each
orientation relative to its own level at T_ref) with the thermal model's line through them
(martinez2022 eq. 1): the reader sees the points the coefficients came from.
"""

from __future__ import annotations

import io
import threading
from typing import Any

from contracts.types import AXES, T_REF_C
from station.records.certificate import Certificate, FitPoint
from station.records.certificate_layout import (BODY_TOP_IN, LEFT_IN, PAGE_H_IN, PAGE_W_IN, RIGHT_IN, Row, _cfg,
                                                layout)

_LOCK = threading.Lock()  # matplotlib's text layout is not fully thread safe (as web/plots.py)
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


__all__ = ["render_pdf"]
