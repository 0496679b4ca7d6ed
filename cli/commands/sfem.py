"""`station sfem LOG.csv [--json] [--norm-only]`: sensor frame error model of a log's static positions.

The same pipeline as the station's own SFEM analysis (station/science/sfem_record.py): a log with a
`position` column (a run exported from the station) is fitted on its placed samples, the reference
direction of each from its position; static intervals are found automatically
(station/science/static_detect.py), averaged per fixture position and per temperature step
(temp_c clusters); one SFEM per step, and with several steps the polynomial of each parameter over
temperature (sensors2023 eq. 8).

Sign conventions of what is printed: A maps raw readings (after the bias b is removed) to g, so
scale is g per raw unit; bias b is the raw reading at zero g, in g; non-orthogonality and
misalignment are small angles in deg (sensors2023 eq. 1, A = M C S). The thermal drift is printed in
the thermal calibration's convention (martinez2022 eq. 1, as `station calibrate`: TDSF is the drift
of the output per g, so a part whose output falls as it warms has a negative TDSF), not as the
slope of S, which has the opposite sign (station/science/sfem_thermal.py module doc). Every +- is
1 sigma.
"""

from __future__ import annotations

import argparse
import json
import math
import sys

import numpy as np

from contracts.json_safe import plain_json
from cli.commands.log_import import add_import_arguments, read_any_log
from contracts.types import T_REF_C
from station.science.sfem import DEFAULT_REF_SIGMA_DEG
from station.science.sfem_model import MISALIGNMENT_NOTE, SfemFit
from station.science.sfem_record import SfemRecordResult, fit_sfem_record
from station.science.static_detect import StaticDetectConfig
from contracts.types import StationError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", help="log file with static positions (CSV, design 5.1)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    parser.add_argument(
        "--norm-only", action="store_true",
        help="fit from the gravity norm alone, ignoring ref_x/y/z (misalignment is then not determined)",
    )  # fmt: skip
    parser.add_argument(
        "--ref-sigma-deg", type=float, default=None,
        help="random error of each reference direction, deg, where a temperature step has too few positions "
             f"to measure it on its own residuals (default {DEFAULT_REF_SIGMA_DEG:g}; a station profile's "
             "sfem_ref_sigma_deg)",
    )  # fmt: skip
    parser.add_argument(
        "--t-ref-c", type=float, default=T_REF_C,
        help=f"reference temperature: the headline step is the one nearest it and the thermal model is centred "
             f"on it (default {T_REF_C:g}; a station profile's sfem_reference_temp_c)",
    )  # fmt: skip
    parser.add_argument("--temp-gap-c", type=float, default=3.0, help="temperature gap that starts a new step (C)")
    parser.add_argument("--window", type=int, default=StaticDetectConfig.window_samples, help="static detector window (samples)")
    parser.add_argument("--min-samples", type=int, default=StaticDetectConfig.min_samples, help="shortest static interval (samples)")
    add_import_arguments(parser)


def _fit_lines(f: SfemFit) -> list[str]:
    lines = [
        f"temperature {f.temp_c:.2f} C  {f.method} fit  {f.n_positions} positions  "
        f"|a|-1g RMSE before {f.rmse_before_mg:.3f} mg  after {f.rmse_after_mg:.4f} mg (in-sample)"
        + ("" if f.rmse_heldout_mg is None else f"  held-out {f.rmse_heldout_mg:.4f} mg ({f.heldout_method})")
        + ("" if f.rmse_direction_mg is None else f"  direction RMSE {f.rmse_direction_mg:.3f} mg")
    ]
    axes = ("x", "y", "z")
    if f.goodness is not None:
        lines.append(f"  fit check: {f.goodness.words}")
    if f.ref_sigma_deg is not None:
        rms = "" if f.residual_direction_deg is None else \
            f" (direction residual {float(np.sqrt(np.mean(f.residual_direction_deg ** 2))):.3g} deg RMS)"
        lines.append(f"  reference direction error {f.ref_sigma_deg:.2g} deg beyond the noise{rms}, {f.ref_sigma_source}")
    lines.append("  scale (g per raw unit)  " + "  ".join(f"{a} {s:.6f}+-{e:.1e}" for a, s, e in zip(axes, f.scale, f.sigma["scale"])))
    lines.append("  bias b (g, the raw reading at zero g)  " + "  ".join(f"{a} {b:+.6f}+-{e:.1e}" for a, b, e in zip(axes, f.b, f.sigma["b"])))
    names = ("yx", "zx", "zy")
    lines.append(
        "  non-orthogonality deg  "
        + "  ".join(f"{n} {math.degrees(v):+.4f}+-{math.degrees(e):.4f}" for n, v, e in zip(names, f.nonorthogonality, f.sigma["alpha"]))
    )
    if f.misalignment_determined:
        lines.append(
            "  misalignment rotvec deg  "
            + "  ".join(
                f"{a} {math.degrees(v):+.4f}+-{math.degrees(e):.4f}"
                for a, v, e in zip(axes, f.misalignment_rotvec_rad, f.sigma["rotvec_rad"])
            )
        )
    else:
        lines.append("  misalignment: NOT DETERMINED (identity) - " + MISALIGNMENT_NOTE.split(": ", 1)[1])
    lines.append("  A = " + "; ".join(" ".join(f"{v:+.6f}" for v in row) for row in f.A))
    return lines


CONVENTIONS = (
    "conventions: A = M C S maps a raw reading, after the bias b, to g (sensors2023 eq. 1); scale S in g per raw "
    "unit (above 1: the axis reads low); bias b the raw reading at zero g; non-orthogonality C = [[1,0,0],"
    "[yx,1,0],[zx,zy,1]] (a positive yx adds +x into the calibrated y); misalignment the rotation vector of M "
    "(right-handed, sensor frame to the fixture's frame); thermal drift in station calibrate's TDSF/TDB "
    "convention; +- is 1 sigma"
)


def format_text(res: SfemRecordResult, serial: str) -> str:
    lines = [f"serial {serial or '?'}  static intervals {res.n_static_intervals}  temperature steps {len(res.fits)}  "
             f"headline step {res.main.temp_c:.2f} C (nearest {res.t_ref_c:g} C)", CONVENTIONS]
    for f in res.fits:
        lines.append("")
        lines.extend(_fit_lines(f))
    if res.thermal is not None:
        th = res.thermal
        lo, hi = th.temp_range_c
        lines.append("")
        lines.append(
            f"thermal model: degree-{th.degree} polynomial of (T - {th.t_ref_c:g} C) per parameter, "
            f"{len(th.temps_c)} steps {lo:.1f}..{hi:.1f} C"
        )
        drift = th.drift_at_t_ref()
        if drift is not None:
            lines.append(f"  drift at {th.t_ref_c:g} C in the thermal calibration's convention (martinez2022 eq. 1, "
                         "as station calibrate):")
            lines.append("    TDSF (ppm/C)  " + "  ".join(
                f"{a} {v:+.1f}+-{e:.1f}" for a, v, e in zip("xyz", drift["tdsf_ppm_per_c"], drift["tdsf_sigma_ppm_per_c"])))
            lines.append("    TDB (mg/C)    " + "  ".join(
                f"{a} {v:+.4f}+-{e:.4f}" for a, v, e in zip("xyz", drift["tdb_mg_per_c"], drift["tdb_sigma_mg_per_c"])))
            lines.append(f"    (+- {drift['sigma_covers']})")
            lines.append("    (the same as slopes of the SFEM's own parameters, the opposite sign for the scale: "
                         "dS/dT / S (ppm/C) " + "  ".join(f"{v:+.1f}" for v in drift["dscale_dT_ppm_of_scale_per_c"])
                         + "; db/dT (mg/C) " + "  ".join(f"{v:+.4f}" for v in drift["db_dT_mg_per_c"]) + ")")
    notes = list(dict.fromkeys([n for f in res.fits for n in f.notes] + res.notes))
    if res.skipped_steps:
        for s in res.skipped_steps:
            lines.append(f"skipped step at {s['temp_c']:.1f} C: {s['n_positions']} positions ({s['reason']})")
    if notes:
        lines.append("")
        lines.extend(f"note: {n}" for n in notes)
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    # bounded memory on a long log (issue 40): only the columns the fit reads are kept (no lamp;
    # no ref_x/y/z for --norm-only), and the arrays, read for this call alone, are compacted to the
    # placed rows in place (fit_sfem_record consume) rather than copied
    log = read_any_log(args.log, args, keep_optional=("position",) if args.norm_only else ("position", "ref_dir"))
    if len(log) == 0:
        raise StationError(f"{args.log}: no data rows")
    placed = log.position is not None and bool((np.asarray(log.position) >= 0).any())
    if not args.norm_only and log.ref_dir is None and not placed:
        raise StationError(f"{args.log}: no ref_x,ref_y,ref_z columns and no placed position column; add them or "
                           "use --norm-only")
    if args.ref_sigma_deg is not None and not args.ref_sigma_deg > 0:
        raise StationError("--ref-sigma-deg must be > 0")
    if args.window < 4 or args.min_samples < 2:
        raise StationError("--window must be >= 4 and --min-samples >= 2")
    cfg = StaticDetectConfig(window_samples=args.window, min_samples=args.min_samples)
    res = fit_sfem_record(
        log.time_s, log.acc_g, log.temp_c,
        None if args.norm_only else log.ref_dir, log.position,
        norm_only=args.norm_only, ref_sigma_deg=args.ref_sigma_deg, config=cfg, temp_gap_c=args.temp_gap_c,
        t_ref_c=args.t_ref_c, consume=True,
    )  # fmt: skip
    if args.json:
        out = {"serial": log.serial, "sensor": log.meta.get("sensor", ""), **res.to_json()}
        json.dump(plain_json(out), sys.stdout, indent=2, allow_nan=False)
        sys.stdout.write("\n")
    else:
        print(format_text(res, log.serial))
    return 0
