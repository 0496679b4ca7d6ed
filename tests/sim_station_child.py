"""A simulated station in its own process, for tests that kill and restart the daemon: the boards
(ptys, slcan), the Modbus server and the physics keep running while the daemon is dead, as real
hardware would. Writes OUT.json ({"config": station config dict, "truths": {slot: ...}}), prints
READY, and runs until SIGTERM.

    python tests/sim_station_child.py OUT.json --serial 3 --can 1 --speed 120 --seed 8
"""

from __future__ import annotations

import argparse
import asyncio
import json
import signal

from drivers.sim.station_sim import SimStation
from cli.commands.demo import sim_config, truth_by_slot


async def main(args: argparse.Namespace) -> None:
    async with SimStation(n_serial=args.serial, n_can=args.can, seed=args.seed, speed=args.speed) as sim:
        cfg = sim_config(sim, speed=args.speed, db_url="sqlite://")
        truths = {
            slot: {"serial": t.serial, "tdb_mg_per_c": [float(x) for x in t.tdb_mg_per_c],
                   "tdsf_ppm_per_c": [float(x) for x in t.tdsf_ppm_per_c]}
            for slot, t in truth_by_slot(sim).items()
        }
        with open(args.out, "w") as f:
            json.dump({"config": cfg, "truths": truths}, f)
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop.set)
        print("READY", flush=True)
        await stop.wait()


if __name__ == "__main__":
    p = argparse.ArgumentParser()
    p.add_argument("out")
    p.add_argument("--serial", type=int, default=3)
    p.add_argument("--can", type=int, default=1)
    p.add_argument("--speed", type=float, default=120.0)
    p.add_argument("--seed", type=int, default=8)
    asyncio.run(main(p.parse_args()))
