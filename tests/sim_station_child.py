"""A simulated station in its own process, for tests that kill and restart the daemon: the boards
(ptys, slcan), the Modbus server and the physics keep running while the daemon is dead, as real
hardware would. Writes OUT.json ({"config": station config dict, "truths": {slot: ...}}), prints
READY, and runs until SIGTERM.

    python tests/sim_station_child.py OUT.json --serial 3 --can 1 --speed 120 --seed 8

--real-plant: the plant never waits for the station (real boards do not; by default the simulated
plant holds its clock while the daemon is behind, which hides an overloaded station) and each
serial board's transmit buffer holds about a second of its sending, as a real one's few KiB do at
its real rate (--tx-buffer), so a station that does not read in time loses samples there, as
sequence gaps. At SIGTERM, OUT.json.end holds each serial
slot's bytes the board could not send (the truth of what the station lost).
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
        if args.real_plant:
            sim.backpressure_bytes = 1 << 62
            # a transmit buffer that holds about a second of what the device sends (a real board's
            # few KiB at its real rate; the simulated plant delivers in ticks, so less would drop a
            # tick's burst however fast the station reads), or --tx-buffer bytes per board
            one_s = sim.world.odr_hz * args.speed
            for b in sim.serial_boards:
                b.port.max_out_bytes = args.tx_buffer or max(4096, int(one_s * 44))
            adapter = getattr(sim, "_adapter", None)
            if adapter is not None and hasattr(adapter, "port"):
                adapter.port.max_out_bytes = max(4096, int(one_s * 24 * max(1, args.can)))
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
        with open(args.out + ".end", "w") as f:
            json.dump({"bytes_dropped": {slot: b.port.bytes_dropped for slot, b in
                                         zip((s["name"] for s in cfg["slots"]), sim.serial_boards)}}, f)


if __name__ == "__main__":
    p = argparse.ArgumentParser()
    p.add_argument("out")
    p.add_argument("--serial", type=int, default=3)
    p.add_argument("--can", type=int, default=1)
    p.add_argument("--speed", type=float, default=120.0)
    p.add_argument("--seed", type=int, default=8)
    p.add_argument("--real-plant", action="store_true", help="the plant never waits; small board buffers")
    p.add_argument("--tx-buffer", type=int, default=0,
                   help="a serial board's transmit buffer with --real-plant (default: about 1 s of its sending)")
    asyncio.run(main(p.parse_args()))
