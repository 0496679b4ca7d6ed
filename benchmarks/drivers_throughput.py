"""Throughput of the board links, simulated board side and driver side in one process (one core).

    .venv/bin/python benchmarks/drivers_throughput.py [--quick]

Prints frames/s through N serial pty boards, through the slcan pty adapter (python-can's slcan
interface reads byte by byte, so it is the slower link), through python-can's virtual bus, and
how far a SimStation with 64 serial boards keeps up with a given speed factor.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from drivers.can_board import CanBoard, CanBus  # noqa: E402
from drivers.serial_board import SerialBoard  # noqa: E402
from drivers.sim.serial_pty import SimSerialBoard  # noqa: E402
from drivers.sim.slcan_pty import SimCanBoard, SimCanHub, SlcanPtyAdapter, VirtualCanBridge  # noqa: E402
from drivers.sim.station_sim import SimStation  # noqa: E402
from contracts.types import Identity  # noqa: E402

IDENT = Identity("BENCH", "LIS3DSH", "1", 60.0, 1.0, 0.0, 3.125)


def _samples(n):
    k = np.arange(n)
    return k / 3.125, np.stack([k % 2000 - 1000, -(k % 3000), 16000 + k % 11], axis=1), k % 40


async def _drain(drivers, want, timeout_s=120.0):
    got = [0] * len(drivers)

    async def one(i, d):
        end = time.perf_counter() + timeout_s
        while got[i] < want and time.perf_counter() < end:
            got[i] += len(await d.read_block(0.5))

    await asyncio.gather(*(one(i, d) for i, d in enumerate(drivers)))
    return sum(got)


async def serial_boards(n_boards, n_samples, chunk=200):
    sims = [SimSerialBoard(IDENT) for _ in range(n_boards)]
    for s in sims:
        s.start()
    drvs = [SerialBoard(s.path) for s in sims]
    for d in drvs:
        await d.open()
        await d.start()
    t, acc, tc = _samples(n_samples)

    async def feeder():
        for a in range(0, n_samples, chunk):
            for s in sims:
                s.feed(t[a : a + chunk], acc[a : a + chunk], tc[a : a + chunk])
            await asyncio.sleep(0)

    t0 = time.perf_counter()
    _, total = await asyncio.gather(feeder(), _drain(drvs, n_samples))
    dt = time.perf_counter() - t0
    lost = sum(d.stats.samples_lost for d in drvs)
    for d in drvs:
        await d.close()
    for s in sims:
        s.close()
    print(f"serial pty  {n_boards:3d} boards: {total:8d} frames in {dt:6.2f} s = {total / dt:9.0f} frames/s (lost {lost})")


async def can_boards(kind, n_boards, n_samples):
    hub = SimCanHub()
    sims = [hub.add(SimCanBoard(i + 1, IDENT)) for i in range(n_boards)]
    if kind == "slcan":
        adapter = SlcanPtyAdapter(hub)
        bus = CanBus("slcan", adapter.path, 500_000, sleep_after_open=0)
    else:
        adapter = VirtualCanBridge(hub, "bench")
        bus = CanBus("virtual", "bench", None)
    adapter.start()
    drvs = [CanBoard(bus, i + 1) for i in range(n_boards)]
    for d in drvs:
        await d.open()
        await d.start()
    await asyncio.sleep(0.3)
    t, acc, tc = _samples(n_samples)
    t0 = time.perf_counter()
    for s in sims:
        s.feed(t, acc, tc)
    total = await _drain(drvs, n_samples)
    dt = time.perf_counter() - t0
    lost = sum(d.stats.samples_lost for d in drvs)
    await bus.close()
    adapter.close()
    print(f"CAN {kind:7s} {n_boards:3d} boards: {total:8d} frames in {dt:6.2f} s = {total / dt:9.0f} frames/s (lost {lost})")


async def station(n_serial, speed, wall_s):
    async with SimStation(n_serial=n_serial, n_can=0, seed=1, speed=speed) as sim:
        drvs = [SerialBoard(p) for p in sim.serial_ports]
        for d in drvs:
            await d.open()
            await d.start()
        c0 = time.process_time()
        t0 = time.perf_counter()
        got = [0] * len(drvs)

        async def one(i, d):
            while time.perf_counter() - t0 < wall_s:
                got[i] += len(await d.read_block(0.2))

        await asyncio.gather(*(one(i, d) for i, d in enumerate(drvs)))
        dt = time.perf_counter() - t0
        cpu = time.process_time() - c0
        due = dt * speed * sim.world.odr_hz * n_serial
        print(
            f"SimStation {n_serial} serial boards at speed {speed:g}: {sum(got)} samples in {dt:.1f} s "
            f"({sum(got) / dt:.0f}/s, {100 * sum(got) / due:.0f}% of due), CPU {100 * cpu / dt:.0f}% of one core"
        )


async def main(quick):
    n = 2000 if quick else 20000
    for nb in (1, 16, 64):
        await serial_boards(nb, n if nb == 1 else n // 4)
    for nb in (4, 32):
        await can_boards("slcan", nb, 500 if quick else 2000)
    await can_boards("virtual", 32, 500 if quick else 2000)
    await station(64, 100, 3 if quick else 10)


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    asyncio.run(main(ap.parse_args().quick))
