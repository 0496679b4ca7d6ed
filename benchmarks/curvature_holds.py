"""How often is a part held for curvature? (docs/verdicts.md "Curvature")

Linear parts (no curvature in the simulator's truth) and parts whose true bias curvature bows
`--bow-factor` x the limit over the operating range (every axis), LIS3DSH class, realistic noise,
the fast-thermal profile (benchmarks/coverage.py's simulation). Each part's bow checks are judged
with the product's own limit (station/decisions/limits.py: 3 mg, k = 2, held only when the bow is
`evidence_sigma` of its sigmas from zero) and, for comparison, with the plain guard band the
station used before (no evidence needed).

    .venv/bin/python benchmarks/curvature_holds.py [--linear 200] [--curved 48] [--seed 3]

Prints the hold rate of linear parts (a part is held when any axis's bow check is not pass) and
the detection rate per axis of the curved parts, for both rules. Not a timed test: ~0.4 s of CPU
per part.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from coverage import simulate  # noqa: E402
from station.decisions.limits import default_products  # noqa: E402
from station.decisions.verdicts import judge, thermal_measurements  # noqa: E402


def bow_outcomes(pop: list[dict], evidence: bool) -> list[list[str]]:
    """Per part, the outcome of each axis's bow check (pass / marginal / fail)."""
    spec = default_products()["LIS3DSH"] if "LIS3DSH" in default_products() else next(iter(default_products().values()))
    limit = next(lim for lim in spec.limits if lim.measurement == "bow_mg")
    if not evidence:
        limit = limit.model_copy(update={"evidence_sigma": 0.0})
    out = []
    for d in pop:
        ms = [m for m in thermal_measurements(d["calibration"]) if m.name == "bow_mg"]
        out.append([judge(m, limit, spec.guard_sigma).outcome for m in ms])
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--linear", type=int, default=200)
    ap.add_argument("--curved", type=int, default=48)
    ap.add_argument("--bow-factor", type=float, default=2.0, help="true bow of the curved parts / the 3 mg limit")
    ap.add_argument("--seed", type=int, default=3)
    args = ap.parse_args(argv)
    t0 = time.process_time()
    lin = simulate(args.linear, args.seed)
    cur = simulate(args.curved, args.seed + 500, bow_mg=3.0 * args.bow_factor)
    print(f"{args.linear} linear + {args.curved} curved (bow {3.0 * args.bow_factor:g} mg, limit 3 mg) simulated "
          f"LIS3DSH parts, fast-thermal, seed {args.seed}")
    print(f"{'rule':34s} {'linear parts held':>18s} {'curved axes held/failed':>24s}")
    for name, ev in (("evidence 4 sigma + k=2 band (now)", True), ("k=2 band only (before)", False)):
        lo = bow_outcomes(lin, ev)
        co = bow_outcomes(cur, ev)
        held = sum(any(o != "pass" for o in axes) for axes in lo)
        det = [o != "pass" for axes in co for o in axes]
        print(f"{name:34s} {held:>7d} of {len(lo):<4d} {held / max(len(lo), 1):6.1%}"
              f" {sum(det):>9d} of {len(det):<4d} {sum(det) / max(len(det), 1):6.1%}")
    print(f"[{time.process_time() - t0:.1f} s CPU]")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
