"""`station sfem LOG.csv [--json] [--norm-only]`: sensor frame error model of a log's static positions.

Static intervals are found automatically (station/science/static_detect.py), averaged per fixture
position (the `position` column groups them when present) and per temperature step (temp_c
clusters); one SFEM per step, and with several steps the polynomial of each parameter over
temperature (sensors2023 eq. 8).
"""

from __future__ import annotations

import argparse
import json
import math
import sys

import numpy as np

from contracts.json_safe import plain_json
from station.commands.log_import import add_import_arguments, read_any_log
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
        "--ref-sigma-deg", type=float, default=DEFAULT_REF_SIGMA_DEG,
        help=f"assumed random error of each reference direction, deg (default {DEFAULT_REF_SIGMA_DEG:g})",
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
    lines.append("  scale  " + "  ".join(f"{a} {s:.6f}+-{e:.1e}" for a, s, e in zip(axes, f.scale, f.sigma["scale"])))
    lines.append("  bias   " + "  ".join(f"{a} {b:+.6f}+-{e:.1e}" for a, b, e in zip(axes, f.b, f.sigma["b"])))
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


def format_text(res: SfemRecordResult, serial: str) -> str:
    lines = [f"serial {serial or '?'}  static intervals {res.n_static_intervals}  temperature steps {len(res.fits)}"]
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
        for name, unit, k in (("scale", "ppm/C", 1e6), ("b", "mg/C", 1e3)):
            slope = th.coef[name][1] * k if th.degree >= 1 else np.zeros(3)
            lines.append(f"  d{name}/dT at {th.t_ref_c:g} C ({unit}): " + "  ".join(f"{v:+.3f}" for v in slope))
    notes = list(dict.fromkeys([n for f in res.fits for n in f.notes] + res.notes))
    if res.skipped_steps:
        for s in res.skipped_steps:
            lines.append(f"skipped step at {s['temp_c']:.1f} C: {s['n_positions']} positions ({s['reason']})")
    if notes:
        lines.append("")
        lines.extend(f"note: {n}" for n in notes)
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    log = read_any_log(args.log, args)
    if len(log) == 0:
        raise StationError(f"{args.log}: no data rows")
    if not args.norm_only and log.ref_dir is None:
        raise StationError(f"{args.log}: no ref_x,ref_y,ref_z columns; add them or use --norm-only")
    if args.window < 4 or args.min_samples < 2:
        raise StationError("--window must be >= 4 and --min-samples >= 2")
    cfg = StaticDetectConfig(window_samples=args.window, min_samples=args.min_samples)
    res = fit_sfem_record(
        log.time_s, log.acc_g, log.temp_c,
        None if args.norm_only else log.ref_dir, log.position,
        norm_only=args.norm_only, ref_sigma_deg=args.ref_sigma_deg, config=cfg, temp_gap_c=args.temp_gap_c,
    )  # fmt: skip
    if args.json:
        out = {"serial": log.serial, "sensor": log.meta.get("sensor", ""), **res.to_json()}
        json.dump(plain_json(out), sys.stdout, indent=2, allow_nan=False)
        sys.stdout.write("\n")
    else:
        print(format_text(res, log.serial))
    return 0
