"""Record batches the way a line runs them, with the real daemon on a simulated station, for the
replay tests: an operator at the page turning the plate (no fixture), a board refusing its
calibration write, an operator abort, a board unplugged mid-batch.

Everything goes through what a line has: the prompt's answer (Station.answer_prompt, as the page's
route), the operator's abort, and the simulated boards' own fault switches (board_nvm, disconnect).
"""

from __future__ import annotations

import asyncio
import subprocess
import sys
from dataclasses import dataclass

SPEED = 300.0


@dataclass
class Script:
    profile: str = "fast-thermal"
    fixture: bool = True
    refuse_write_slot: int | None = None  # board index whose calibration writes are refused
    abort_at_sample_s: float | None = None  # operator aborts once the batch's sample clock passes this
    unplug_slot: int | None = None  # board index whose cable is pulled (its pty closes) ...
    unplug_at_sample_s: float = 300.0  # ... once the batch's sample clock passes this
    operator_delay_s: float = 1.0  # wall seconds the operator takes to turn the plate
    n_serial: int = 3
    n_can: int = 1
    seed: int = 3


async def _record(url: str, sc: Script) -> dict:
    from drivers.sim.operator import operator_confirms, operator_hands
    from drivers.sim.station_sim import SimStation
    from cli.commands.demo import sim_config
    from station.config import parse_config
    from station.daemon.storage import open_database
    from station.daemon.supervisor import Station

    async with SimStation(n_serial=sc.n_serial, n_can=sc.n_can, seed=sc.seed, speed=SPEED) as sim:
        cfg = parse_config(sim_config(sim, speed=SPEED, db_url=url, fixture=sc.fixture), "<recorder>")
        db = open_database(cfg.database_url, station=cfg.name)
        station = Station(cfg, db=db)
        tasks = [asyncio.create_task(operator_hands(station.bus, sim.world))]
        try:
            await station.start()
            if sc.refuse_write_slot is not None:
                sim.board(sc.refuse_write_slot).cal.refuse_writes(1000)
            bid = station.start_batch(sc.profile, None, "page operator")
            tasks.append(asyncio.create_task(operator_confirms(
                lambda: station.prompt(bid), lambda pid: station.answer_prompt(bid, pid, "done", by="Ana"),
                delay_s=sc.operator_delay_s)))
            unplugged = aborted = False
            while True:
                try:
                    await station.wait_batch(bid, timeout_s=0.05)
                    break
                except asyncio.TimeoutError:
                    pass
                clock = station.batch_status(bid)["sample_time_s"]
                if sc.abort_at_sample_s is not None and not aborted and clock > sc.abort_at_sample_s:
                    station.abort(bid, "operator stop", by="Ana")
                    aborted = True
                if sc.unplug_slot is not None and not unplugged and clock > sc.unplug_at_sample_s:
                    sim.board(sc.unplug_slot).disconnect()
                    unplugged = True
            await station.flush_db()
            st = station.batch_status(bid)
            return {"batch": bid, "state": st["state"],
                    "slots": {s["slot"]: {"serial": s["serial"], "state": s["state"],
                                          "verdict": (s.get("decision") or {}).get("verdict")} for s in st["slots"]}}
        finally:
            for t in tasks:
                t.cancel()
            await station.close("recorded")
            db.dispose()


def record(url: str, script: Script) -> dict:
    return asyncio.run(_record(url, script))


def station_cli(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cli", *args], capture_output=True, text=True,
                          timeout=timeout)


def all_fail_limits(path, sensors) -> str:
    """A config whose TDB limit no calibrated part meets (|TDB| <= 0.001 mg/C): every part the
    recording judged pass or marginal becomes fail."""
    limit = ('[[products.{s}.limits]]\nmeasurement = "tdb_mg_per_c"\nlow = -0.001\nhigh = 0.001\n'
             'label = "TDB"\n')
    path.write_text(
        'name = "tight"\n[lamp]\ntcp = {host = "127.0.0.1", port = 1502}\nunit = 1\n'
        '[[slots]]\nname = "s01"\nserial = "/dev/null"\n'
        + "".join(f'[products.{s}]\nsensor = "{s}"\nversion = "tight-1"\n' + limit.format(s=s)
                  for s in sorted(set(sensors))))
    return str(path)
