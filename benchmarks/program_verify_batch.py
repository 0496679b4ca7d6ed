"""Program and verify on a 12-DUT simulated batch: verified E before/after per DUT and axis, and the
minutes the program-and-verify tail adds to a fast-thermal batch.

    .venv/bin/python benchmarks/program_verify_batch.py [--serial 8] [--can 4] [--curved 2] [--speed 120] [--seed 14]

The real daemon (Station) runs `fast-thermal-verified` against simulated boards on ptys, CAN boards
behind an slcan adapter pty, and the Modbus relay/fixture on 127.0.0.1, with SQLite on disk. `--curved`
DUTs (the last serial board, the last CAN board, ...) get the simulator's curved bias drift (bias_t2). Printed per DUT: programmed
(attempts, CRC), compensation on, E before (uncompensated, first pass, eq. 10 over 70 C) and E
verified (compensated output during the verification heat), the ratio, pass/flag. Then the time
budget in SAMPLE time (what a real station spends): the first pass (fast-thermal), the program step
and the verification heat, in minutes. Prints, never asserts.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from drivers.sim.physics import draw_population  # noqa: E402
from drivers.sim.station_sim import SimStation  # noqa: E402
from cli.commands.demo import sim_config  # noqa: E402
from station.config import parse_config  # noqa: E402
from station.daemon.storage import open_database  # noqa: E402
from station.daemon.supervisor import Station
from contracts.types import AXES  # noqa: E402


async def run(n_serial: int, n_can: int, n_curved: int, speed: float, seed: int) -> None:
    n = n_serial + n_can
    plain = draw_population(n, seed)
    curved = draw_population(n, seed, effects=("bias_t2",))
    # curved parts: the last serial board, then the last CAN board, then the ones before them
    order = [i for pair in zip(range(n_serial - 1, -1, -1), range(n - 1, n_serial - 1, -1)) for i in pair]
    order += [i for i in range(n - 1, -1, -1) if i not in order]
    idx = set(order[:n_curved])
    truths = [curved[i] if i in idx else plain[i] for i in range(n)]
    curved_serials = {truths[i].serial for i in idx}
    with tempfile.TemporaryDirectory() as tmp:
        async with SimStation(n_serial=n_serial, n_can=n_can, seed=seed, speed=speed, truths=truths) as sim:
            # lamp on-time limit raised: on a loaded machine wall x speed overstates the on-time
            cfg = parse_config(sim_config(sim, speed=speed, db_url=f"sqlite:///{tmp}/pv.db",
                                          limits={"lamp_max_on_s": 9000.0}), "<bench>")
            db = open_database(cfg.database_url)
            st = Station(cfg, db=db)
            await st.start()
            try:
                t0 = time.monotonic()
                bid = st.start_batch("fast-thermal-verified", None, "benchmark")
                status = await st.wait_batch(bid, timeout_s=3600)
                wall = time.monotonic() - t0
                seq = st.batches[bid]
            finally:
                await st.close()
                db.dispose()
    prof = seq.profile
    pi = prof.program_step
    hi = pi + 1
    print(f"batch {bid}: {status['state']} {status['error'] or ''} ({n_serial} serial + {n_can} CAN, "
          f"{n_curved} with bias_t2, speed {speed:g}, wall {wall:.0f} s)")
    head = (f"{'slot':5} {'serial':9} {'prog':5} {'tries':5} {'comp':4} "
            + " ".join(f"Eb_{a}".rjust(7) for a in AXES) + " " + " ".join(f"Ev_{a}".rjust(7) for a in AXES)
            + "  ratio_max  verdict")
    print(head)
    befores, afters, first_pass, heat_s = [], [], [], []
    for d in seq.duts:
        p, v = d.program or {}, d.verification or {}
        eb, ea = v.get("e_before_mg") or {}, v.get("e_after_mg") or {}
        ratio = max((ea[a] / eb[a]) for a in AXES) if eb and ea and all(eb.get(a) for a in AXES) else float("nan")
        verdict = ("PASS" if v.get("passed") else "FLAG") if v else (d.fault_reason or d.state)[:60]
        tag = " (bias_t2)" if d.serial in curved_serials else ""
        print(f"{d.slot:5} {d.serial or '':9} {'yes' if p.get('programmed') else 'no':5} {p.get('attempts', 0):5} "
              f"{'on' if p.get('comp') else 'off':4} "
              + " ".join(f"{eb.get(a, float('nan')):7.2f}" for a in AXES) + " "
              + " ".join(f"{ea.get(a, float('nan')):7.2f}" for a in AXES) + f"  {ratio:9.3f}  {verdict}{tag}")
        if v and d.serial not in curved_serials:
            befores.append([eb[a] for a in AXES])
            afters.append([ea[a] for a in AXES])
        for flag in v.get("flags", []):
            print(f"      {flag}")
        if d.serial in curved_serials:
            t = next(t for t in truths if t.serial == d.serial)
            c2 = t.effects["bias_t2"]["c2_mg_per_c2"]
            print("      simulator truth bias_t2 c2 (mg/C^2): " + " ".join(f"{a} {c:+.4f}" for a, c in zip(AXES, c2)))
        w = d.step_windows
        if not v:  # time budget from the DUTs that went through the whole profile
            continue
        if d.t0 is not None and pi - 1 in w:
            first_pass.append(w[pi - 1][1] - d.t0)
        if hi in w:
            heat_s.append(w[hi][1] - w[hi][0])
    if befores:
        b, a = np.array(befores), np.array(afters)
        print(f"linear DUTs ({len(b)}): E before mean {b.mean():.1f} mg (max {b.max():.1f}); "
              f"verified E mean {a.mean():.2f} mg (max {a.max():.2f}); mean ratio {np.mean(a / b):.3f}")
    prog_wall = _program_wall_s(seq)
    if first_pass and heat_s:
        fp, ht = max(first_pass) / 60, max(heat_s) / 60
        print(f"verification heat per DUT (sample time): median {np.median(heat_s) / 60:.1f} min, "
              f"min {min(heat_s) / 60:.1f}, max {ht:.1f} min")
        pr = prog_wall / 60  # analysis + writes run in real time, whatever the simulation speed
        print(f"first pass (sample time) {fp:.1f} min; program step {prog_wall:.1f} s wall (analysis of the first pass, "
              f"drain, write, read back, COMP); verification heat {ht:.1f} min sample time (slowest DUT)")
        print(f"program and verify adds {pr + ht:.1f} min to a {fp:.0f} min batch ({100 * (pr + ht) / fp:.0f} %)")


def _program_wall_s(seq) -> float:
    """Wall seconds the sequencer spent in its `programming` state (from its transition history)."""
    t_in = next((t for t, a, b in seq.history if b == "programming"), None)
    t_out = next((t for t, a, b in seq.history if a == "programming"), None)
    return (t_out - t_in) if t_in is not None and t_out is not None else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--serial", type=int, default=8)
    ap.add_argument("--can", type=int, default=4)
    ap.add_argument("--curved", type=int, default=2)
    ap.add_argument("--speed", type=float, default=120.0)
    ap.add_argument("--seed", type=int, default=14)
    a = ap.parse_args()
    asyncio.run(run(a.serial, a.can, a.curved, a.speed, a.seed))


if __name__ == "__main__":
    main()
