"""PNG plots of a diagnosis (design 7), with matplotlib's object API (no pyplot global state).

Per DUT: measured vs model; residual vs temperature, vs time and vs dT/dt, each point coloured by
its orientation (the legend names it as the CLI does: "position 0 (P)") and marked heating (filled
triangle up), cooling (open triangle down) or steady (dot), so that a loop that differs between
orientations or between heating and cooling shows; residual vs orientation (per orientation and
axis, a box of the residual's 1-minute means with their mean +- standard deviation beside it);
residual vs acceleration; and the Allan deviation of the residual against the sensor's own noise (a
static segment of the log; station/diagnostics/noise_view.py). Per report: ranking bars (flags in
words), error staircase.
Sample-level series are drawn as 1-minute means (the report's RMS windows): 940 points for a
15-hour log instead of 176 000, and the quantity the RMS figures are computed on.

Residual = measured - model, in mg, always; the current model (baseline + added effects) is drawn
in colour, the baseline's residual in grey behind it when effects were added.
"""

from __future__ import annotations

import io
import textwrap
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from contracts.types import AXES, StationError
from station.diagnostics.noise_view import _position_name

DUT_PLOTS = ("measured_vs_model", "residual_vs_temperature", "residual_vs_time", "residual_vs_rate",
             "residual_vs_orientation", "residual_vs_acceleration", "allan_deviation")
REPORT_PLOTS = ("ranking", "staircase")
PLOTS = DUT_PLOTS + REPORT_PLOTS
RATE_STEADY_C_PER_MIN = 0.05
# heating / cooling / steady: the marker (the colour is the orientation's)
DIRECTIONS = (("heating", "^", True, f"heating (dT/dt > {RATE_STEADY_C_PER_MIN:g} C/min)"),
              ("cooling", "v", False, f"cooling (dT/dt < -{RATE_STEADY_C_PER_MIN:g} C/min)"),
              ("steady", ".", True, "steady"))
BASELINE_GREY = "#cccccc"


def orientation_names(d) -> list[str]:
    """The orientations of a prepared log (DutData) as the CLI says them: "position 0 (P)", or
    "orientation o0" for an orientation found by clustering (a log without a position column)."""
    return [_position_name(lab) for lab in d.pos_labels]


def _orientation_colours(n: int) -> list:
    from matplotlib import colormaps

    cmap = colormaps["tab10" if n <= 10 else "tab20"]
    return [cmap(k % cmap.N) for k in range(n)]


def _list_words(s: str) -> str:
    items = [x for x in s.split(",") if x]
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1] if items else ""


def flag_words(flag: str) -> str:
    """A ranking row's flag (ranking.py, staircase.py) in words: never the raw label on a page."""
    head, _, rest = flag.partition(":")
    if flag == "no_evidence":
        return "no evidence on its own against the baseline"
    if head == "confusable_with":
        return f"confusable with {_list_words(rest)} on this data"
    if head == "explained_by":
        return f"explained by {_list_words(rest)}, admitted before it"
    if head == "stands_for_it":
        return f"{_list_words(rest)}, admitted, stands for it (confusable on this data: only one goes in)"
    if head == "masked":
        kind, _, who = rest.partition(":")
        if kind == "evidence_given":
            return f"its evidence shows only once {_list_words(who)} is in the model"
        if kind == "admitted_with":
            return f"admitted together with {_list_words(who)} (each hides the other on the held-out legs)"
        return f"masked: {kind.replace('_', ' ')}" + (f" {who}" if who else "")
    return head.replace("_", " ") + (f": {rest}" if rest else "")  # a flag not known here: its own words


def _short_flag(flag: str) -> str:
    """The ranking bars' label of a flag: a few words."""
    head, _, rest = flag.partition(":")
    if flag == "no_evidence":
        return "no evidence"
    short = {"confusable_with": "confusable with {}", "explained_by": "explained by {}",
             "stands_for_it": "{} stands for it"}
    if head in short:
        return short[head].format(_list_words(rest))
    if head == "masked":
        kind, _, who = rest.partition(":")
        if kind == "evidence_given":
            return f"shows once {_list_words(who)} is in"
        if kind == "admitted_with":
            return f"with {_list_words(who)}"
    return textwrap.shorten(flag_words(flag), 48, placeholder="...")


def _wmean(d, x: np.ndarray) -> np.ndarray:
    """Means of x (n,) or (n, k) over the report's RMS windows, NaN-aware."""
    x2 = x.reshape(d.n, -1)
    ok = ~np.isnan(x2).any(axis=1)
    w = d.window[ok]
    cnt = np.bincount(w, minlength=int(d.block_window.max()) + 1).astype(float)
    out = np.stack([np.bincount(w, weights=x2[ok, k], minlength=cnt.size) for k in range(x2.shape[1])], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = out / cnt[:, None]
    out[cnt == 0] = np.nan
    return out if x.ndim > 1 else out[:, 0]


def _rate_c_per_min(d) -> np.ndarray:
    """dT/dt of the smoothed measured temperature, C/min, per sample."""
    if d.n < 3:
        return np.zeros(d.n)
    return np.gradient(d.temp_smooth_c, d.time_s) * 60.0


def _series(report, k: int) -> dict:
    d = report.data[k]
    fit = report.model.fits[k]
    acc0_mg = np.nan_to_num(fit.acc0_g)[d.pos] * 1000.0
    model_mg = d.acc_mg - report.model.resid[k]
    rate = _rate_c_per_min(d)
    return {
        "t_h": _wmean(d, d.time_s) / 3600.0,
        "temp": _wmean(d, d.temp_smooth_c),
        "rate": _wmean(d, rate),
        "acc_g": _wmean(d, d.acc_mg) / 1000.0,
        "meas_drift": _wmean(d, d.acc_mg - acc0_mg),
        "model_drift": _wmean(d, model_mg - acc0_mg),
        "res": _wmean(d, report.model.resid[k]),
        "res_base": _wmean(d, report.baseline.resid[k]) if report.model.effects else None,
        # a window never straddles a constant-orientation run (segmentation.py): its orientation code
        "pos": np.rint(_wmean(d, d.pos.astype(float))).astype(int),
    }


def _model_label(report) -> str:
    return "baseline" + "".join(f" + {e}" for e in report.model.effects)


def _axes3(fig: Figure, sharex: bool = True):
    return fig.subplots(3, 1, sharex=sharex)


def plot_measured_vs_model(report, k: int = 0) -> Figure:
    s = _series(report, k)
    fig = Figure(figsize=(9, 7), layout="constrained")
    for i, ax in enumerate(_axes3(fig)):
        ax.plot(s["t_h"], s["meas_drift"][:, i], ".", ms=2, color="black", label="measured")
        ax.plot(s["t_h"], s["model_drift"][:, i], "-", lw=1, color="#ff7f0e", label=f"model ({_model_label(report)})")
        ax.set_ylabel(f"{AXES[i]}: acc - Acc0 (mg)")
        ax.grid(alpha=0.3)
    ax.set_xlabel("time (h)")
    fig.axes[0].legend(loc="best", fontsize=8)
    fig.suptitle(f"{report.data[k].serial}: measured vs model (thermal part; 1-min means)")
    return fig


def _direction_masks(rate: np.ndarray) -> dict[str, np.ndarray]:
    return {"heating": rate > RATE_STEADY_C_PER_MIN, "cooling": rate < -RATE_STEADY_C_PER_MIN,
            "steady": np.abs(rate) <= RATE_STEADY_C_PER_MIN}


def _legend_by_orientation(fig: Figure, names: list[str], cols: list, present: np.ndarray, dirs: set[str],
                           baseline: bool) -> None:
    handles = [Line2D([], [], ls="", marker="s", ms=7, color=cols[p], label=names[p])
               for p in range(len(names)) if present[p]]
    handles += [Line2D([], [], ls="", marker=mk, ms=6, color="black", mfc="black" if filled else "none", label=lab)
                for key, mk, filled, lab in DIRECTIONS if key in dirs]
    if baseline:
        handles.append(Line2D([], [], ls="", marker=".", ms=6, color=BASELINE_GREY, label="baseline residual"))
    fig.legend(handles=handles, loc="outside right upper", fontsize=8, title="orientation / direction",
               title_fontsize=8)


def _residual_panels(report, k: int, x: np.ndarray | None, xlabel: str, title: str, by_orientation: bool = False,
                     per_axis_x: np.ndarray | None = None) -> Figure:
    """Three panels (x, y, z) of the residual's 1-minute means against x. by_orientation: each point
    coloured by its orientation and marked by heating / cooling / steady."""
    s = _series(report, k)
    d = report.data[k]
    names = orientation_names(d)
    cols = _orientation_colours(len(names))
    fig = Figure(figsize=(11 if by_orientation else 9, 7), layout="constrained")
    masks = _direction_masks(s["rate"])
    dirs_seen: set[str] = set()
    present = np.zeros(len(names), bool)
    for i, ax in enumerate(_axes3(fig, sharex=per_axis_x is None)):
        xi = per_axis_x[:, i] if per_axis_x is not None else x
        if s["res_base"] is not None:
            ax.plot(xi, s["res_base"][:, i], ".", ms=2, color=BASELINE_GREY, label="baseline residual")
        if by_orientation:
            for p in range(len(names)):
                at_p = s["pos"] == p
                for key, mk, filled, _ in DIRECTIONS:
                    m = at_p & masks[key] & np.isfinite(s["res"][:, i])
                    if not m.any():
                        continue
                    present[p] = True
                    dirs_seen.add(key)
                    ax.plot(xi[m], s["res"][m, i], ls="", marker=mk, ms=2.5 if key == "steady" else 3.5,
                            color=cols[p], mfc=cols[p] if filled else "none", mew=0.8,
                            alpha=0.6 if key == "steady" else 0.9)
        else:
            ax.plot(xi, s["res"][:, i], ".", ms=3, color="#2ca02c", label=f"residual ({_model_label(report)})")
        ax.axhline(0.0, color="black", lw=0.5)
        ax.set_ylabel(f"{AXES[i]}: residual (mg)")
        ax.grid(alpha=0.3)
        if per_axis_x is not None:
            ax.set_xlabel(f"{AXES[i]} {xlabel}")
    if per_axis_x is None:
        fig.axes[-1].set_xlabel(xlabel)
    if by_orientation:
        _legend_by_orientation(fig, names, cols, present, dirs_seen, s["res_base"] is not None)
    else:
        fig.axes[0].legend(loc="best", fontsize=8, markerscale=3)
    fig.suptitle(f"{d.serial}: residual = measured - model ({_model_label(report)}) vs {title} (1-min means)")
    return fig


def plot_residual_vs_temperature(report, k: int = 0) -> Figure:
    s = _series(report, k)
    return _residual_panels(report, k, s["temp"], "temperature (C)", "temperature", by_orientation=True)


def plot_residual_vs_time(report, k: int = 0) -> Figure:
    s = _series(report, k)
    return _residual_panels(report, k, s["t_h"], "time (h)", "time", by_orientation=True)


def plot_residual_vs_rate(report, k: int = 0) -> Figure:
    s = _series(report, k)
    return _residual_panels(report, k, s["rate"], "dT/dt (C/min)", "dT/dt", by_orientation=True)


def plot_residual_vs_orientation(report, k: int = 0) -> Figure:
    """Per axis, per orientation: a box of the residual's 1-minute means (median, quartiles, whiskers
    at 1.5 IQR) and beside it their mean +- one standard deviation; the baseline's in grey on the
    left when effects were added. An offset that differs between orientations, or a spread that does,
    is what a missing orientation-dependent effect (scale, cross-axis) leaves."""
    s = _series(report, k)
    d = report.data[k]
    names = orientation_names(d)
    cols = _orientation_colours(len(names))
    P = len(names)
    fig = Figure(figsize=(max(7.0, 2.0 + 1.1 * P), 7), layout="constrained")
    xs = np.arange(P, dtype=float)
    has_base = s["res_base"] is not None
    for i, ax in enumerate(_axes3(fig)):
        for p in range(P):
            r = s["res"][s["pos"] == p, i]
            r = r[np.isfinite(r)]
            if has_base:
                rb = s["res_base"][s["pos"] == p, i]
                rb = rb[np.isfinite(rb)]
                if rb.size:
                    bp = ax.boxplot([rb], positions=[xs[p] - 0.28], widths=0.2, showfliers=False, patch_artist=True)
                    for b in bp["boxes"]:
                        b.set(facecolor=BASELINE_GREY, edgecolor="#888888")
            if not r.size:
                continue
            bp = ax.boxplot([r], positions=[xs[p]], widths=0.3, showfliers=False, patch_artist=True)
            for b in bp["boxes"]:
                b.set(facecolor=cols[p], alpha=0.5, edgecolor=cols[p])
            for med in bp["medians"]:
                med.set(color="black")
            ax.errorbar([xs[p] + 0.28], [float(np.mean(r))], yerr=[float(np.std(r))], fmt="o", ms=4, capsize=3,
                        color=cols[p])
        ax.axhline(0.0, color="black", lw=0.5)
        ax.set_ylabel(f"{AXES[i]}: residual (mg)")
        ax.grid(alpha=0.3, axis="y")
        ax.set_xlim(-0.6, P - 0.4)
    last = fig.axes[-1]
    last.set_xticks(xs, names, rotation=20 if P > 4 else 0, ha="right" if P > 4 else "center")
    last.set_xlabel("orientation")
    handles = [Line2D([], [], ls="", marker="s", ms=8, color="#777777", alpha=0.6,
                      label="box: median, quartiles, whiskers 1.5 IQR of the 1-min means"),
               Line2D([], [], ls="-", marker="o", ms=4, color="#777777", label="mean +- 1 standard deviation")]
    if has_base:
        handles.append(Line2D([], [], ls="", marker="s", ms=8, color=BASELINE_GREY, label="baseline residual"))
    fig.axes[0].legend(handles=handles, loc="best", fontsize=8)
    fig.suptitle(f"{d.serial}: residual = measured - model ({_model_label(report)}) per orientation (1-min means)")
    return fig


def plot_residual_vs_acceleration(report, k: int = 0) -> Figure:
    s = _series(report, k)
    return _residual_panels(report, k, None, "acceleration (g)", "acceleration", per_axis_x=s["acc_g"])


def _arr(x) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in (x or [])], dtype=float)


def _tau(t: float) -> str:
    return f"{t:.0f}" if t >= 100 else f"{t:.2g}"


def _axis_verdict(ax_name: str, e: dict) -> str:
    c = e.get("comparison")
    if not c or c.get("at_sensor_noise") is None:
        return f"{ax_name}: residual alone (no sensor reference)"
    if c["at_sensor_noise"]:
        return f"{ax_name}: at the sensor's noise"
    if c["unmodelled_signal"]:
        rng = ", ".join(f"{_tau(a)}-{_tau(b)} s" for a, b in c["unmodelled_ranges_s"])
        return f"{ax_name}: unmodelled signal {rng} (up to {c['max_unmodelled_ratio']:.2g}x)"
    rng = ", ".join(f"{_tau(a)}-{_tau(b)} s" for a, b in c["ranges_s"])
    return f"{ax_name}: above {rng}, the model's own noise"


def plot_allan_deviation(report, k: int = 0) -> Figure:
    """Log-log Allan deviation per axis: the residual (with 1-sigma intervals) against the sensor's
    static segment (band), the model's own input noise, and faint -1/2, 0, +1/2 reference slopes."""
    nv = report.noise(k)
    fig = Figure(figsize=(12, 5.2), layout="constrained")
    panels = fig.subplots(1, 3, sharey=True)
    for ax, (name, e) in zip(panels, nv["axes"].items()):
        r, st, mn = e["residual"], e.get("static"), e.get("model_noise")
        tr, ar = _arr(r["taus_s"]), _arr(r["adev_mg"])
        ref_t, ref_a = (_arr(st["taus_s"]), _arr(st["adev_mg"])) if st else (tr, ar)
        if st:
            ax.fill_between(ref_t, _arr(st["lo_mg"]), _arr(st["hi_mg"]), color="#888888", alpha=0.25, lw=0)
            ax.plot(ref_t, ref_a, "o-", ms=3, lw=1, color="black", label="sensor: static segment (1-sigma band)")
            c = e.get("comparison") or {}
            bound = np.array([x == "bound" for x in c.get("reference", [])], bool)
            if bound.any():
                last = int(np.flatnonzero(~bound)[-1])
                bt = _arr(c["taus_s"])[last:]
                ax.plot(bt, _arr(c["static_adev_mg"])[last:], "--", lw=1, color="black",
                        label="sensor bound beyond the static segment (x sqrt(tau))")
        if mn and len(mn["taus_s"]):
            ax.plot(_arr(mn["taus_s"]), _arr(mn["adev_mg"]), ":", lw=1.2, color="#ff7f0e",
                    label="model's own noise (per-sample temperature)")
        if tr.size:
            yerr = np.vstack([ar - _arr(r["lo_mg"]), _arr(r["hi_mg"]) - ar])
            ax.errorbar(tr, ar, yerr=yerr, fmt="s-", ms=3, lw=1, capsize=2, color="#2ca02c",
                        label=f"residual ({_model_label(report)})")
            c = e.get("comparison") or {}
            if c.get("taus_s"):
                ct = _arr(c["taus_s"])
                ca = _arr(c["residual_adev_mg"])
                un = np.array(c["unmodelled"], bool)
                own = np.array(c["above"], bool) & ~un
                if un.any():
                    ax.plot(ct[un], ca[un], "o", ms=8, mfc="none", color="#d62728", label="unmodelled signal")
                if own.any():
                    ax.plot(ct[own], ca[own], "o", ms=8, mfc="none", color="#ff7f0e",
                            label="above: the model's own noise")
        ok = np.isfinite(ref_a) & (ref_a > 0)
        ys = np.concatenate([ar, ref_a])  # the model's own noise may fall below: clipped
        ys = ys[np.isfinite(ys) & (ys > 0)]
        if ok.any():  # reference slopes: the sensor's terms where present, else through the curve's minimum
            i0 = int(np.nanargmin(np.where(ok, ref_a, np.inf)))
            terms = e.get("terms") or e.get("residual_terms") or {}
            t_all = np.concatenate([tr, ref_t])
            tt = np.geomspace(np.nanmin(t_all), np.nanmax(t_all), 50)
            for p, term, at_1, lab in ((-0.5, "white", lambda v: v, "slopes -1/2 (white), 0 (bias instability), "
                                        "+1/2 (random walk)"),
                                       (0.0, "bias_instability", lambda v: 0.664 * v, None),
                                       (0.5, "random_walk", lambda v: v / np.sqrt(3.0), None)):
                t_ = terms.get(term) or {}
                y1 = at_1(t_["value"]) if t_.get("present") and t_.get("value") else ref_a[i0] / ref_t[i0] ** p
                ax.plot(tt, y1 * tt ** p, "--", lw=0.8, color="#bbbbbb", label=lab, zorder=0)
        if ys.size:
            ax.set_ylim(ys.min() / 3.0, ys.max() * 2.0)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("averaging time tau (s)")
        ax.grid(alpha=0.3, which="both")
        ax.set_title(textwrap.fill(_axis_verdict(name, e), 48), fontsize=8)
    panels[0].set_ylabel("Allan deviation (mg)")
    panels[0].legend(loc="lower left", fontsize=7)
    fig.suptitle(textwrap.fill(nv["statement"], 150), fontsize=9)
    return fig


def plot_ranking(report) -> Figure:
    rows = report.ranking
    fig = Figure(figsize=(10, 0.45 * max(len(rows), 2) + 1.6), layout="constrained")
    ax = fig.add_subplot()
    names = [r["effect"] for r in rows][::-1]
    vals = [r["heldout_rms_mg"] or 0.0 for r in rows][::-1]
    cols = []
    for r in rows[::-1]:
        if r["admitted"]:
            cols.append("#2ca02c")
        elif any(f.startswith("confusable") for f in r["flags"]):
            cols.append("#ff7f0e")
        else:
            cols.append("#aaaaaa")
    ax.barh(names, vals, color=cols)
    ax.axvline(report.baseline.heldout_rms_mg, color="black", ls="--", lw=1, label="baseline held-out")
    for y, r in enumerate(rows[::-1]):
        words = [_short_flag(f) for f in r["flags"]]
        tag = "; ".join((["admitted"] if r["admitted"] else []) + words) or "not admitted"
        ax.text(vals[y], y, f"  {tag}", va="center", fontsize=7)
    top = max([v for v in vals if np.isfinite(v)] + [report.baseline.heldout_rms_mg or 0.0, 1e-9])
    ax.set_xlim(0.0, 1.9 * top)  # room for the words right of the longest bar
    ax.set_xlabel("held-out RMS with the candidate added (mg)")
    ax.set_title("candidate effects (green admitted, orange confusable, grey not admitted)")
    ax.legend(loc="lower right", fontsize=8)
    return fig


def plot_staircase(report) -> Figure:
    st = report.staircase
    fig = Figure(figsize=(8, 4.5), layout="constrained")
    ax = fig.add_subplot()
    x = np.arange(len(st))
    ins = [s["rms_mg"] or np.nan for s in st]
    ho = [s["heldout_rms_mg"] or np.nan for s in st]
    ax.step(x, ins, where="mid", color="#1f77b4", label="in-sample")
    ax.step(x, ho, where="mid", color="#d62728", label="held-out")
    ax.plot(x, ins, "o", color="#1f77b4")
    ax.plot(x, ho, "s", color="#d62728")
    ax.set_xticks(x, [s["model"] for s in st], rotation=20, ha="right")
    ax.set_yscale("log")
    ax.set_ylabel(f"RMS of {report.rms_basis} (mg)")
    ax.set_title("error staircase: baseline -> + effect -> ...")
    ax.grid(alpha=0.3, which="both")
    ax.legend()
    return fig


_DUT_FUNCS = {
    "measured_vs_model": plot_measured_vs_model,
    "residual_vs_temperature": plot_residual_vs_temperature,
    "residual_vs_time": plot_residual_vs_time,
    "residual_vs_rate": plot_residual_vs_rate,
    "residual_vs_orientation": plot_residual_vs_orientation,
    "residual_vs_acceleration": plot_residual_vs_acceleration,
    "allan_deviation": plot_allan_deviation,
}


def figure(report, name: str, dut: int = 0) -> Figure:
    if name in _DUT_FUNCS:
        if not 0 <= dut < len(report.data):
            raise StationError(f"no DUT {dut} in this diagnosis")
        return _DUT_FUNCS[name](report, dut)
    if name == "ranking":
        return plot_ranking(report)
    if name == "staircase":
        return plot_staircase(report)
    raise StationError(f"unknown plot {name!r} (known: {', '.join(PLOTS)})")


def png_bytes(fig: Figure, dpi: int = 100) -> bytes:
    buf = io.BytesIO()
    FigureCanvasAgg(fig)
    fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()


def render_png(report, name: str, dut: int = 0) -> bytes:
    return png_bytes(figure(report, name, dut))


def write_plots(report, out_dir: str | Path) -> list[Path]:
    """Every plot as PNG in out_dir: <serial>_<plot>.png per DUT, ranking.png, staircase.png. The
    serial is data (a log's header): contracts.filenames.safe_path makes it a safe name inside out_dir."""
    from contracts.filenames import safe_path

    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StationError(f"{out}: cannot create plot directory ({exc.strerror or exc})") from None
    paths = []
    for k, d in enumerate(report.data):
        for name in DUT_PLOTS:
            p = safe_path(out, d.serial, f"_{name}.png")
            p.write_bytes(render_png(report, name, k))
            paths.append(p)
    for name in REPORT_PLOTS:
        p = safe_path(out, name, ".png")
        p.write_bytes(render_png(report, name))
        paths.append(p)
    return paths


__all__ = ["PLOTS", "DUT_PLOTS", "REPORT_PLOTS", "figure", "render_png", "write_plots", "png_bytes", "flag_words",
           "orientation_names"]
