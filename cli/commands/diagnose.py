"""`station diagnose LOG.csv [LOG2.csv ...] [--add EFFECT ...] [--json] [--plots DIR]` (design 5.2, 7).

Fits the baseline thermal model (martinez2022 eq. 1) to one DUT's log, or to several DUTs of one
batch together (each DUT its own parameters, the effect structure shared), ranks the candidate
effects of the library (station/diagnostics/effects.py) by held-out gain, and with `--add` refits
with the chosen effects and prints the error staircase baseline -> +effect -> ...

    station diagnose SIM0001.csv                       # ranking of missing effects
    station diagnose SIM0001.csv --add thermal_lag     # staircase and fitted tau with uncertainty
    station diagnose *.csv --add bias_t2 --json        # a batch, design 5.2 JSON
    station diagnose LOG.csv --effects-file my_effect.py --add my_effect --plots out/
    station diagnose LOG.csv --add bias_t2 --save-model SIM0001.model.json

Residual = measured - model, in mg, always. The report ends with the noise statement per DUT
(station/diagnostics/noise_view.py: the residual's Allan deviation against a static segment of the
log); --json has it under "noise", per serial.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from contracts.types import StationError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("logs", nargs="+", metavar="LOG.csv", help="log file(s) of one DUT or of one batch (CSV, design 5.1)")
    parser.add_argument("--add", action="append", default=[], metavar="EFFECT",
                        help="add an effect to the model (repeatable; order = staircase order)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON (design 5.2)")
    parser.add_argument("--plots", metavar="DIR", help="write PNG plots to DIR")
    parser.add_argument("--effects-file", action="append", default=[], metavar="PY",
                        help="Python file registering user effects (repeatable; see docs/diagnostics.md)")
    parser.add_argument("--candidates", metavar="LIST",
                        help="comma-separated effects to rank (default: every registered effect)")
    parser.add_argument("--basis", choices=("window", "sample"), default="window",
                        help="RMS of 1-minute residual means (default) or of every sample")
    from cli.commands.log_import import add_import_arguments

    add_import_arguments(parser)
    parser.add_argument("--no-cache", action="store_true",
                        help="do not read or write the ranking cache (a first run's ranking, reused by the next "
                             "--add; $STATION_DIAGNOSE_CACHE: its folder, or off; see docs/diagnostics.md)")
    parser.add_argument("--save-model", metavar="PATH",
                        help="save the fitted model (baseline + added effects): a file for one log, "
                             "a directory (one <serial>.model.json per DUT, the serial made a safe file "
                             "name) for several")


def _split(items: list[str]) -> list[str]:
    return [x.strip() for item in items for x in item.split(",") if x.strip()]


def _f(x, fmt: str = ".4f", none: str = "-") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return none
    return format(x, fmt)


def _fmt_value(entry: dict) -> str:
    v, s = entry.get("value"), entry.get("sigma")
    if v is None:
        return "-"
    if s is None:
        return f"{v:.6g}"
    return f"{v:.6g} +- {s:.2g} (1 sigma)"


def format_report(doc: dict) -> str:
    """The human-readable report: ranking, flags, staircase, fitted effect parameters."""
    lines = []
    lines.append(f"DUT(s): {', '.join(doc['serials'])}   residual = {doc['residual']}   RMS of {doc['rms_basis']}")
    left = doc.get("leftover") or {}
    if left.get("statement"):
        # said first: whether anything the model does not explain remains on the held-out legs
        lines.append(("LEFTOVER: " if left.get("above_floor") else "leftover: ") + left["statement"])
        if left.get("above_floor") and left.get("carrying"):
            lines.append(f"  plots that show it: {', '.join(left['carrying'])} (--plots DIR)")
    b = doc["baseline"]
    lines.append(f"baseline (eq. 1: Acc0 per orientation, TDB, TDSF): in-sample {_f(b['rms_mg'])} mg, "
                 f"held-out {_f(b['heldout_rms_mg'])} mg")
    nm = doc.get("noise_model") or {}
    if nm:
        lines.append(f"noise model of the residual: {nm['residual']}")
        lines.append(f"held-out: {nm['heldout']}")
    drift = doc.get("drift") or {}
    for serial, axes in (drift.get("tdsf_identifiable") or {}).items():
        bad = [ax for ax, ok in axes.items() if not ok]
        if bad:
            tot = (doc.get("baseline_parameters", {}).get(serial, {}).get("baseline", {})
                   .get("total_drift_mg_per_c", {}))
            per = "  ".join(f"{ax} {_fmt_value(tot[ax])}" for ax in bad if ax in tot)
            lines.append(f"  {serial}: TDSF NOT IDENTIFIABLE on axis {','.join(bad)} (one Acc0 per axis in this log); "
                         f"total drift TDB + TDSF Acc0 [mg/C]: {per}")
            lines.append(f"    test that would identify it: {drift.get('test_to_identify')}")
    lines.append("")
    lines.append("candidate effects, best held-out first (each alone against the baseline):")
    lines.append(f"  {'effect':<20}{'held-out mg':>12}{'gain mg':>10}{'legs better':>12}{'delta BIC':>12}{'LR p':>10}  "
                 f"{'admitted':<9}flags")
    for r in doc["ranking"]:
        legs = f"{r['legs_better']}/{r['legs']}" if r.get("legs") else "-"
        lines.append(f"  {r['effect']:<20}{_f(r['heldout_rms_mg']):>12}{_f(r['heldout_gain_mg']):>10}{legs:>12}"
                     f"{_f(r['delta_bic'], '.1f'):>12}{_f(r['score_p'], '.2g'):>10}  "
                     f"{'yes' if r['admitted'] else 'no':<9}{' '.join(r['flags'])}")
        if r.get("shape"):
            lines.append(f"  {'':<20}shape: {r['shape']}")
        if r.get("why"):
            lines.append(f"  {'':<20}why not: {r['why']}")
        if r.get("same_as"):
            lines.append(f"  {'':<20}one term -- {r['same_as']}")
    for c in doc["confusable"]:
        lines.append(f"  CONFUSABLE: {' and '.join(c['effects'])} (cos {c['cosine']}): {c['reason']}; "
                     f"to separate: {c['to_separate']}")
    for u in doc["unidentifiable"]:
        lines.append(f"  NOT IDENTIFIABLE: {u['effect']}: {u['reason']}; needs {u['needs']}; "
                     f"test that would identify it: {u['test_to_identify']}")
    admitted = doc.get("admitted", [r["effect"] for r in doc["ranking"] if r["admitted"]])
    lines.append(f"  admitted: {', '.join(admitted) if admitted else 'none (no effect passes the gate)'}")
    auto = doc.get("admitted_staircase") or []
    if len(auto) > 1:
        lines.append("  admitted staircase (each step against the model before it; reproduce with "
                     + " ".join(f"--add {e}" for e in admitted) + "):")
        for s_ in auto:
            extra = (f"  delta BIC {_f(s_.get('delta_bic'), '.1f')}, LR p {_f(s_.get('score_p'), '.2g')}"
                     if "delta_bic" in s_ else "")
            shape = f"  ({s_['shape']})" if s_.get("shape") else ""
            lines.append(f"    {s_['model']:<26}held-out {_f(s_['heldout_rms_mg'])} mg{extra}{shape}")
    lines.append("")
    lines.append("error staircase:")
    lines.append(f"  {'model':<28}{'in-sample mg':>14}{'held-out mg':>13}")
    for s in doc["staircase"]:
        lines.append(f"  {s['model']:<28}{_f(s['rms_mg']):>14}{_f(s['heldout_rms_mg']):>13}"
                     + (f"  WARNING: {s['warning']}" if s.get("warning") else ""))
    if len(doc["staircase"]) == 1:
        lines.append("  (add effects with --add EFFECT to refit and extend the staircase)")
    params = doc["model"].get("parameters", {})
    if doc["model"]["effects"]:
        lines.append("")
        lines.append("fitted effect parameters (1-sigma from the GLS fit under the residual's noise model):")
        for serial, p in params.items():
            for eff, vals in p["effects"].items():
                for pname, entry in vals.items():
                    if "value" in entry:
                        lines.append(f"  {serial}  {eff}.{pname}: {_fmt_value(entry)}")
                    else:
                        per = "  ".join(f"{ax} {_fmt_value(e)}" for ax, e in entry.items())
                        lines.append(f"  {serial}  {eff}.{pname}: {per}")
    noise = doc.get("noise") or {}
    if noise:
        lines.append("")
        lines.append("noise: Allan deviation of the residual against the sensor's own noise (a static segment of the log):")
        for nv in noise.values():
            lines.append(f"  {nv['statement']}")
            for ax, e in nv["axes"].items():
                lines.append(f"    {ax}: {e['statement']}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    if not args.no_cache:  # the sources the ranking cache's key names, read before they are imported
        from station.diagnostics import disk_cache

        disk_cache.code_digest()
    from station.diagnostics.effects import get_effect, load_effects_file
    from station.diagnostics.ranking import diagnose

    for f in args.effects_file:
        load_effects_file(f)
    add = _split(args.add)
    for a in add:
        get_effect(a)
    candidates = _split([args.candidates]) if args.candidates else None
    for c in candidates or ():
        get_effect(c)
    logs = [_read(p, args) for p in args.logs]
    for path, lg in zip(args.logs, logs):
        if not lg.meta.get("serial"):
            lg.meta["serial"] = Path(path).stem
    serials = [lg.serial for lg in logs]
    if len(set(serials)) != len(serials):
        raise StationError(f"the same DUT serial appears twice among the logs ({', '.join(serials)})")
    with _ranking_cache(args):  # the logs are read for this call alone: prepared in place (bounded memory)
        report = diagnose(logs, add=add, candidates=candidates, basis=args.basis, consume_logs=True)
    doc = report.to_json()
    doc["noise"] = {d.serial: report.noise(k) for k, d in enumerate(report.data)}
    if args.plots:
        from station.diagnostics.plots import write_plots

        doc["plots"] = [str(p) for p in write_plots(report, args.plots)]
    if args.save_model:
        doc["saved_models"] = [str(p) for p in _save_models(report, Path(args.save_model))]
    if args.json:
        json.dump(doc, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        print(format_report(doc))
        for p in doc.get("plots", []):
            print(f"plot: {p}")
        for p in doc.get("saved_models", []):
            print(f"model saved: {p}")
    return 0


def _ranking_cache(args: argparse.Namespace):
    """The ranking cache on disk (station/diagnostics/disk_cache.py) for this command's diagnose():
    a first run ranks the candidates and keeps the ranking, `--add EFFECT` on the same log(s),
    candidates, effects and software reuses it and fits only the added models."""
    from contextlib import nullcontext

    if args.no_cache:
        return nullcontext()
    from station.diagnostics import disk_cache
    from station.version import software_version

    return disk_cache.enabled(version=software_version())


def _read(path: str, args: argparse.Namespace):
    """A station log (design 5.1), or with any import option a delimited log from another tool;
    a log without the station's columns is imported with the column names recognised. Both are
    checked before any science (cli.commands.log_import.read_any_log)."""
    from cli.commands.log_import import read_any_log

    # only the columns the diagnosis reads (issue 40: ref_x/y/z and lamp are not kept)
    return read_any_log(path, args, keep_optional=("position",))


def _save_models(report, path: Path) -> list[Path]:
    from contracts.filenames import safe_path

    models = report.models()
    try:
        if len(models) == 1 and not path.is_dir():
            path.parent.mkdir(parents=True, exist_ok=True)
            models[0].save(path)
            return [path]
        path.mkdir(parents=True, exist_ok=True)
        out = []
        for m in models:
            p = safe_path(path, m.serial, ".model.json")  # the serial is data: never a path
            m.save(p)
            out.append(p)
        return out
    except OSError as exc:
        raise StationError(f"{path}: cannot save model ({exc.strerror or exc})") from None
