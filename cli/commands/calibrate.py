"""`station calibrate LOG.csv [--json]`: thermal calibration of a recorded fast-thermal log.

The log is checked before any science (units, temperatures, time order, header numbers:
contracts/logfile.py); the import options (--accel-units, --temp-units, --columns, ...) read a log in
other units or from another tool, as `station diagnose` does."""

from __future__ import annotations

import argparse
import json
import sys

from cli.commands.log_import import add_import_arguments, read_any_log
from contracts.types import AXES


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", help="fast-thermal log file (CSV, design 5.1)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    add_import_arguments(parser)


def _fmt_sigma(v: float | None, fmt: str) -> str:
    return "" if v is None else " +- " + format(v, fmt)


def format_table(res: dict) -> str:
    lines = [f"serial {res['serial'] or '?'}  sensor {res['sensor'] or '?'}  samples {res['n_samples']}  "
             f"temperature swing {res['temperature_swing_c']:.1f} C"]
    lines.append("")
    lines.append(f"{'axis':<5}{'method':<11}{'TDB mg/C':>22}{'TDSF ppm/C':>24}")
    for name in AXES:
        for method in ("offline", "streaming"):
            ax = res[method]["axes"][name]
            tdb = f"{ax['tdb_mg_per_c']:.4f}{_fmt_sigma(ax['tdb_sigma_mg_per_c'], '.4f')}"
            tdsf = f"{ax['tdsf_ppm_per_c']:.1f}{_fmt_sigma(ax['tdsf_sigma_ppm_per_c'], '.1f')}"
            flag = "  (positive TDSF clamped to 0)" if ax["tdsf_clamped"] else ""
            lines.append(f"{name if method == 'offline' else '':<5}{method:<11}{tdb:>22}{tdsf:>24}{flag}")
    lines.append(f"(adopted: {res['axes_method']} fit; uncertainties 1-sigma)")
    lines.append("")
    lines.append(f"{'axis':<5}{'orient.':<9}{'TD stream mg/C':>16}{'TD offline mg/C':>17}{'Acc0 stream g':>16}{'Acc0 offline g':>16}")
    for name in AXES:
        off = {o["orientation"]: o for o in res["offline"]["orientations"].get(name, [])}
        for o in res["streaming"]["orientations"].get(name, []):
            f = off.get(o["orientation"])
            lines.append(
                f"{name:<5}{o['orientation']:<9}{o['td_mg_per_c']:>16.4f}"
                f"{(f['td_mg_per_c'] if f else float('nan')):>17.4f}{o['acc0_g']:>16.5f}"
                f"{(f['acc0_g'] if f else float('nan')):>16.5f}"
            )
    lines.append("")
    lines.append(f"{'seg':<5}{'orient.':<9}{'t_start s':>11}{'t_end s':>11}{'temp C':>9}{'ax g':>11}{'ay g':>11}{'az g':>11}")
    for s in res["segments"]:
        lines.append(
            f"{s['index']:<5}{s['orientation']:<9}{s['t_start_s']:>11.1f}{s['t_end_s']:>11.1f}{s['temp_mean_c']:>9.2f}"
            + "".join(f"{v:>11.5f}" for v in s["acc_mean_g"])
        )
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from station.science.thermal_calibration import calibrate  # scipy: imported by the command, not by --help

    # bounded memory on a long log (issue 40): only the columns the calibration reads are kept (not
    # lamp, not ref_x/y/z), and the log, read for this call alone, is compacted to its placed rows
    # in place rather than copied
    res = calibrate(read_any_log(args.log, args, keep_optional=("position",)), consume_log=True)
    if args.json:
        json.dump(res, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        print(format_table(res))
    return 0
