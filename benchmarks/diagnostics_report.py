"""Per-effect figures of model diagnostics on the simulator's validation profile.

For each hidden effect (and the control with none): simulate the `validation` profile, run
`diagnose(..., add=[effect])`, and print the baseline held-out RMS, the held-out RMS after adding
the effect, the honest noise floor (tests/diag_helpers.noise_floor: the true model on the measured
inputs), where the true effect ranked, what was admitted, and the fitted parameters against the truth.

    .venv/bin/python benchmarks/diagnostics_report.py                 # 1 DUT per effect
    .venv/bin/python benchmarks/diagnostics_report.py --duts 8        # a batch of 8 fitted together
    .venv/bin/python benchmarks/diagnostics_report.py --effects bias_t2,thermal_lag --seed 5

RMS on 1-minute residual means ("window", the stringent basis) and per sample (white noise included).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import diag_helpers as H  # noqa: E402
from drivers.sim.physics import HIDDEN_EFFECTS  # noqa: E402
from station.diagnostics.ranking import diagnose  # noqa: E402


def _param_text(rows: list[dict]) -> str:
    out = []
    by = {}
    for r in rows:
        by.setdefault((r["effect"], r["param"].split("[")[0]), []).append(r)
    for (eff, param), rs in by.items():
        if len(rs) == 1 and rs[0]["axis"] is None:
            r = rs[0]
            out.append(f"{param} {r['fit']:.4g}+-{(r['sigma'] or 0):.2g} (true {r['true']:.4g})")
        else:
            err = [abs(r["fit"] - r["true"]) for r in rs if r["fit"] is not None]
            mag = [abs(r["true"]) for r in rs]
            ex = rs[0]
            out.append(f"{param} e.g. {ex['serial']} {ex['axis']} {ex['fit']:.4g} (true {ex['true']:.4g}); "
                       f"max |fit-true| {max(err):.3g} of |true| up to {max(mag):.3g} over {len(rs)} values")
    return "; ".join(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duts", type=int, default=1)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--effects", default="none," + ",".join(HIDDEN_EFFECTS))
    args = ap.parse_args()
    print(f"validation profile, {args.duts} DUT(s) fitted together, seed {args.seed}; RMS in mg "
          f"(window = 1-minute means, sample = per sample)")
    hdr = (f"{'hidden effect':<19}{'rank':>5}{'base HO win':>12}{'after HO win':>13}{'floor win':>10}{'ratio':>7}"
           f"{'after HO smp':>13}{'floor smp':>10}{'time s':>8}  admitted / flags / fitted vs true")
    print(hdr)
    for eff in [e.strip() for e in args.effects.split(",") if e.strip()]:
        effs = () if eff == "none" else (eff,)
        logs, truths = H.validation_logs(effs, n_duts=args.duts, seed=args.seed)
        t0 = time.perf_counter()
        rep = diagnose(logs, add=list(effs))
        dt = time.perf_counter() - t0
        fw = H.pooled_floor(logs, truths, "window")
        fs = H.pooled_floor(logs, truths, "sample")
        names = [r["effect"] for r in rep.ranking]
        rank = names.index(eff) + 1 if eff in names else "-"
        admitted = [r["effect"] for r in rep.ranking if r["admitted"]]
        conf = [c["effects"] for c in rep.confusable]
        extra = f"admitted {admitted or 'none'}" + (f"; confusable {conf}" if conf else "")
        if effs:
            extra += "; " + _param_text(H.compare_params(rep.parameters, truths))
        print(f"{eff:<19}{rank!s:>5}{rep.baseline.heldout_rms_mg:>12.4f}{rep.model.heldout_rms_mg:>13.4f}{fw:>10.4f}"
              f"{rep.model.heldout_rms_mg / fw:>7.3f}{rep.model.heldout_rms_sample_mg:>13.4f}{fs:>10.4f}{dt:>8.1f}  {extra}")
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
