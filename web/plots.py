"""PNG of one run for the operator page: acceleration per axis (raw and thermally compensated)
and temperature against time, with the logged segments shaded. Rendered with matplotlib's
object API (no pyplot global state), so it is safe in the server's thread pool."""

from __future__ import annotations

import io
import threading

import numpy as np

from contracts.types import AXES, T_REF_C

_LOCK = threading.Lock()  # matplotlib's font cache and text layout are not fully thread safe
MAX_POINTS = 4000


def _compensate(acc_g: np.ndarray, temp_c: np.ndarray, tdb_mg_per_c: np.ndarray, tdsf_ppm_per_c: np.ndarray) -> np.ndarray:
    try:
        from station.science.thermal_model import compensate

        return np.asarray(compensate(acc_g, temp_c, tdb_mg_per_c, tdsf_ppm_per_c, t_ref_c=T_REF_C))
    except ImportError:  # science package not built yet: martinez2022 eq. 13 inline
        dt = (temp_c - T_REF_C)[:, None]
        return (acc_g - dt * tdb_mg_per_c * 1e-3) / (1.0 + dt * tdsf_ppm_per_c * 1e-6)


def _decimate(n: int) -> slice:
    return slice(None, None, max(1, n // MAX_POINTS))


def since_first_sample(time_s: np.ndarray, segments: list[dict] | None) -> tuple[np.ndarray, list[dict]]:
    """Board times -> seconds since the run's first sample, segments shifted alike.

    The boards stamp samples with their own clock since power-up: a plot on that axis starts at
    e.g. 73000 s, which says nothing to an operator; the run's own time does."""
    t = np.asarray(time_s, dtype=float)
    t0 = float(t[0]) if len(t) else 0.0
    segs = []
    for seg in segments or []:
        seg = dict(seg)
        for k in ("t_start_s", "t_end_s"):
            if seg.get(k) is not None:
                seg[k] = float(seg[k]) - t0
        segs.append(seg)
    return t - t0, segs


def render_run_png(log, segments: list[dict], thermal_axes: dict | None, title: str = "") -> bytes:
    """log: contracts.logfile.DutLog; segments: dicts with t_start_s/t_end_s; thermal_axes: x/y/z
    -> {tdb_mg_per_c, tdsf_ppm_per_c} or None (then only raw is drawn)."""
    with _LOCK:
        fig = run_figure(log, segments, thermal_axes, title)
        buf = io.BytesIO()
        fig.savefig(buf, format="png")
    return buf.getvalue()


def run_figure(log, segments: list[dict], thermal_axes: dict | None, title: str = ""):
    """The run's matplotlib Figure (render_run_png draws it under the lock): time since the run's
    first sample on the x axis."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    t, segments = since_first_sample(log.time_s, segments)
    acc = np.asarray(log.acc_g, dtype=float).reshape(-1, 3)
    temp = np.asarray(log.temp_c, dtype=float)
    sl = _decimate(len(t))
    comp = None
    if thermal_axes and len(t):
        try:
            tdb = np.array([float(thermal_axes[a]["tdb_mg_per_c"]) for a in AXES])
            tdsf = np.array([float(thermal_axes[a]["tdsf_ppm_per_c"]) for a in AXES])
            if np.all(np.isfinite(tdb)) and np.all(np.isfinite(tdsf)):
                comp = _compensate(acc[sl], temp[sl], tdb, tdsf)
        except (KeyError, TypeError, ValueError):
            comp = None
    fig = Figure(figsize=(10, 7.5), dpi=90)
    FigureCanvasAgg(fig)
    axs = fig.subplots(4, 1, sharex=True, gridspec_kw={"height_ratios": [1, 1, 1, 0.9]})
    colors = ("tab:red", "tab:green", "tab:blue")
    for i, name in enumerate(AXES):
        ax = axs[i]
        ax.plot(t[sl], acc[sl, i], color=colors[i], lw=0.8, alpha=0.55, label=f"{name} raw")
        if comp is not None:
            ax.plot(t[sl], comp[:, i], color="black", lw=0.9, label=f"{name} compensated")
        ax.set_ylabel(f"a{name} (g)")
        ax.grid(alpha=0.3)
    axs[3].plot(t[sl], temp[sl], color="tab:orange", lw=1.0, label="temperature")
    axs[3].set_ylabel("temp (C)")
    axs[3].set_xlabel("time since the run's first sample (s)")
    axs[3].grid(alpha=0.3)
    for k, seg in enumerate(segments or []):
        t0, t1 = seg.get("t_start_s"), seg.get("t_end_s")
        if t0 is None or t1 is None:
            continue
        for ax in axs:
            ax.axvspan(t0, t1, color="tab:purple", alpha=0.18, lw=0, label="logged segment" if k == 0 else None)
    for ax in axs:
        handles, labels = ax.get_legend_handles_labels()
        if handles:
            ax.legend(loc="upper right", fontsize=7, ncol=3)
    if not len(t):
        axs[0].text(0.5, 0.5, "no samples stored for this run", transform=axs[0].transAxes, ha="center")
    fig.suptitle(title or "run")
    fig.tight_layout()
    return fig
