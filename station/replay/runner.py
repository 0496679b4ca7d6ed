"""Run a Recording through the real daemon and compare the outcome (the core of `station replay`).

The station under test is the installed code with the recording's own configuration (limits,
profiles, products, timing from the batch's config snapshot), optionally overridden by another
config file: "which of yesterday's parts would change verdict with this limits set / release?".
The replay batch is stored in `db_url` marked `replay_of` (db/models.Batch): its results get no
result_seq, so the MES never sees them, and they are no attempts, yields or SPC points.
"""

from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import dataclass
from typing import Any

from station.aio import cancel_and_wait
from station.replay.compare import DEFAULT_ATOL, DEFAULT_RTOL, ReplayDiff, compare_outcomes
from station.replay.director import Director
from contracts.recording import Recording
from station.replay.recording import run_outcome
from contracts.types import StationError

log = logging.getLogger(__name__)

# Sections of a station config that decide the outcome; links, tokens and names are the replay's own.
OUTCOME_SECTIONS = ("limits", "profiles", "products")
REPLAY_MIN_STALL_TIMEOUT_S = 60.0  # wall seconds of listening before a replayed board counts as silent
REPLAY_READS_PER_S = 1e6  # reads a second before a replay spaces out small reads: never, in practice
TIMING_KEYS = ("stall_timeout_s", "identify_timeout_s", "fixture_timeout_s", "read_period_s", "plate_again_after_s")


def agree_window(speed: float) -> float:
    """Sample seconds a lamp/fixture disagreement may last before it is reported: a wall-clock
    delay of d s is d x speed sample seconds in compressed time, and the recording's and the
    replay's daemons react with different delays (CPU load, CAN adapter latency), so the
    comparison resolves 1 wall second x speed, and never better than 120 s (two block reads and a
    fixture move at the default x60)."""
    return max(120.0, 1.0 * float(speed))


@dataclass
class ReplayOptions:
    db_url: str
    speed: float = 60.0
    overrides: dict[str, Any] | None = None  # sections of another config (--config)
    rtol: float = DEFAULT_RTOL
    atol: float = DEFAULT_ATOL
    agree_window_s: float | None = None  # None: agree_window(speed)
    can_interface: str = "slcan"
    end_grace_s: float = 15.0  # wall seconds after the recording ran out before the batch is aborted
    max_lead_s: float = 30.0  # sample seconds the replayed boards may run ahead of the daemon (pace_by)
    name: str = "replay"


def replay_config(recording: Recording, sim: Any, opts: ReplayOptions) -> dict:
    """The replay daemon's config: the recording's outcome sections, the simulated links."""
    snap = recording.config_snapshot or {}
    cfg: dict[str, Any] = {k: snap[k] for k in OUTCOME_SECTIONS if snap.get(k)}
    for k, v in (opts.overrides or {}).items():
        if k in OUTCOME_SECTIONS:
            cfg[k] = v
    timing = {k: v for k, v in (snap.get("timing") or {}).items() if k in TIMING_KEYS}
    # A replayed board is a record the director paces: it is silent by design while held at a program
    # stop or a prompt, and on a loaded machine those holds can outlast a line's stall timeout. A
    # record cannot die: a recorded unplug replays as the port closing ("link lost") and a recorded
    # silent board as its record ending, which still faults after this longer timeout.
    timing["stall_timeout_s"] = max(float(timing.get("stall_timeout_s", 10.0)), REPLAY_MIN_STALL_TIMEOUT_S)
    timing.update({k: v for k, v in ((opts.overrides or {}).get("timing") or {}).items() if k in TIMING_KEYS})
    timing["speed"] = opts.speed
    # A replay's world waits on the station (it moves the plate when the station asks), so every
    # delay of a read is replay time: each link is read at its period, never spaced out (design 2.2)
    timing["reads_per_s"] = REPLAY_READS_PER_S
    slots: list[dict] = []
    ports = iter(sim.serial_ports)
    nodes = iter(sim.can_node_ids)
    for d in sim.ordered:
        if d.link == "can":
            slots.append({"name": d.slot, "can": {"interface": sim.can_bus_args["interface"],
                                                   "channel": sim.can_channel, "node": next(nodes)}})
        else:
            slots.append({"name": d.slot, "serial": next(ports)})
    tcp = {"host": sim.modbus_host, "port": sim.modbus_port}
    cfg.update({
        "name": opts.name,
        "database_url": opts.db_url,
        "timing": timing,
        "slots": slots,
        "lamp": {"tcp": tcp, "unit": 1},
        "replay_of": recording.source[:256],
    })
    have = snap.keys() if snap else ("fixture", "thermometer", "chamber")  # logs: every instrument
    for dev, unit in (("fixture", 3), ("thermometer", 2), ("chamber", 4)):
        if dev in have and (snap.get(dev) is not None if snap else True):
            cfg[dev] = {"tcp": tcp, "unit": unit}
    return cfg


async def run_replay(recording: Recording, opts: ReplayOptions, on_started: Any = None) -> ReplayDiff:
    """Replay, wait for the batch to end, compare, store the comparison with the replay batch."""
    from db import repository as R
    from drivers.sim.replay import ReplayStation, recorded_digest
    from station.config import parse_config
    from station.daemon.storage import open_database
    from station.daemon.supervisor import Station

    async with ReplayStation(recording, speed=opts.speed, can_interface=opts.can_interface) as sim:
        cfg = parse_config(replay_config(recording, sim, opts), "<replay>")
        db = open_database(cfg.database_url, station=cfg.name)
        station = Station(cfg, db=db)
        try:
            await station.start()
            batch_id = station.start_batch(recording.profile, None, "replay", by="station replay")
            sim.pace_by(lambda: station.samples_taken(batch_id), opts.max_lead_s)
            director = Director(recording, station, sim, batch_id)
            directing = asyncio.create_task(director.run(), name="replay-director")
            if on_started is not None:
                on_started(batch_id, station, sim)
            t0 = time.monotonic()
            ran_out: float | None = None
            try:
                while True:
                    try:
                        await station.wait_batch(batch_id, timeout_s=0.5)
                        break
                    except asyncio.TimeoutError:
                        pass
                    if directing.done() and directing.exception() is not None:
                        raise directing.exception()  # type: ignore[misc]
                    if sim.world.exhausted and recording.batch_state == "finished":
                        # the recorded batch finished: the replay should too; if it waits for more
                        # (another profile or config), it is ended and the diff says so
                        ran_out = ran_out or time.monotonic()
                        if time.monotonic() - ran_out > opts.end_grace_s:
                            station.abort(batch_id, "the recording ended before the batch finished", by="replay")
                            await station.wait_batch(batch_id, timeout_s=60.0)
                            break
            finally:
                await cancel_and_wait(directing)
            await station.flush_db()
            status = station.batch_status(batch_id)
            wall_s = time.monotonic() - t0
            detail = R.batch_detail(db, batch_id) or {"runs": []}
            after_runs = {r["slot"]: r for r in detail["runs"]}
            duts = []
            plate: dict[str, Any] = {}
            for i, d in enumerate(sim.ordered):
                run = after_runs.get(d.slot)
                after = None if run is None else run_outcome(db, run)
                dd = compare_outcomes(d.slot, d.serial, d.outcome, after, opts.rtol, opts.atol)
                n_sent, crc = sim.world.sent_digest(i)
                dd.samples_identical = n_sent > 0 and (n_sent, crc) == recorded_digest(_prefix(d, n_sent))
                dd.note = f"sent {n_sent} of {len(d)} recorded samples"
                if run is not None and run.get("fault_reason"):
                    dd.note += f"; {run['fault_reason']}"
                duts.append(dd)
                if run is not None and not plate and d.lamp is not None:  # the plate is one: one DUT tells
                    window = opts.agree_window_s if opts.agree_window_s is not None else agree_window(opts.speed)
                    plate = _plate(db, run["id"], d, window, detail,
                                   [st["name"] for st in station.profile(recording.profile)["steps"]])
            diff = ReplayDiff(recording.source, recording.before_label, opts.rtol, opts.atol, duts,
                              agreement=plate or {"agrees": None, "note": "the recording has no lamp/position "
                                                                          "columns: the plate cannot be compared"},
                              replay_batch_id=batch_id, replay_state=status["state"], replay_error=status.get("error"),
                              recorded_state=recording.batch_state,
                              ended_at_recording_end=director.ended_at_recording_end, notes=director.notes)
            samples = sum(sim.world.sent)
            diff.agreement["rate"] = {"wall_s": round(wall_s, 2), "samples_sent": samples,
                                      "samples_per_s": round(samples / wall_s, 1) if wall_s > 0 else None}
            _store_diff(db, batch_id, diff)
            return diff
        finally:
            await station.close("replay finished")
            if hasattr(db, "dispose"):
                db.dispose()


def _plate(db: Any, run_id: int, d: Any, window_s: float, detail: dict | None = None,
           step_names: list[str] | None = None) -> dict:
    from db.export import run_samples
    from station.replay.agreement import describe_episode, plate_agreement, step_at

    smp = run_samples(db, run_id)
    out = plate_agreement(d.time_s, d.lamp, d.position, smp.time_s, smp.lamp, smp.position, window_s)
    out["reference_slot"] = d.slot
    spans = []
    for k, by_slot in ((detail or {}).get("step_windows") or {}).items():
        w = (by_slot or {}).get(d.slot)
        if w and None not in w[:2] and step_names and int(k) < len(step_names):
            spans.append((float(w[0]), float(w[1]), f"{int(k)} '{step_names[int(k)]}'"))
    for dev in ("lamp", "fixture"):
        for ep in (out.get(dev) or {}).get("episodes", []):
            ep["step"] = step_at(spans, (ep["from_s"] + ep["to_s"]) / 2)
            ep["explanation"] = describe_episode(dev, ep, ep["step"])
    return out


def _prefix(d: Any, n: int) -> Any:
    import dataclasses

    return dataclasses.replace(d, time_s=d.time_s[:n], acc_counts=d.acc_counts[:n], temp_counts=d.temp_counts[:n])


def _store_diff(db: Any, batch_id: int, diff: ReplayDiff) -> None:
    from sqlalchemy import update

    from db.models import Batch

    try:
        with db.session() as s:
            s.execute(update(Batch).where(Batch.id == batch_id).values(replay_diff=diff.to_json()))
    except Exception as exc:  # noqa: BLE001 - the diff is printed anyway; say that it is not stored
        raise StationError(f"replay batch {batch_id}: the comparison could not be stored: {exc}") from exc
