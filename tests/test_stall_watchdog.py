"""The "no samples" watchdog blames a board only for the time it had the chance to send.

A station whose own loop is held up (a database call waiting on a lock, a long collection) must
not fault the boards that were streaming all along, and the program step, which stops every
stream to write the calibration, must not turn slow writes into "no samples". A board that really
goes silent is still faulted, after stall_timeout_s of listening.

Real parts: serial boards on pseudo-terminals, the daemon, the Modbus lamp, SQLite on disk. The
loop is held up with a blocking sleep inside it, exactly what a synchronous call does.
"""

from __future__ import annotations

import asyncio
import re
import time

import pytest

from test_daemon_e2e import coil, daemon, wait_for
from drivers.sim.station_sim import SimStation

SPEED = 100.0


@pytest.mark.timeout(180)
async def test_a_held_up_station_does_not_fault_a_streaming_board_and_a_silent_one_still_faults(tmp_path):
    stall_s = 2.5
    async with SimStation(n_serial=3, n_can=0, seed=4, speed=SPEED) as sim:
        async with daemon(sim, tmp_path, SPEED, timing={"stall_timeout_s": stall_s}) as st:
            bid = st.start_batch("fast-thermal", None, "pytest")
            await wait_for(lambda: st.batch_status(bid)["seq_state"] == "logging"
                           and st.batch_status(bid)["step_index"] >= 1, 60, "step 1 logging")
            quiet, dead = sim.board(0), sim.board(1)
            quiet.stop_streaming()
            dead.stop_streaming()
            await asyncio.sleep(0.5)
            time.sleep(stall_s + 0.3)  # the station's loop held up longer than the stall timeout
            await asyncio.sleep(0.3)  # the pumps run at least one more empty read before s01 speaks again
            quiet.muted = False
            status = await st.wait_batch(bid, timeout_s=150)
            by = {s["slot"]: s for s in status["slots"]}
            # s01 was quiet for 0.5 + 2.8 + 0.3 s of wall time, of which the board had the chance to
            # send for about 0.5 + (one read, at most listen_cap_s = 1 s) + 0.3 s < 2.5 s
            assert by["s01"]["state"] == "done", by["s01"]
            assert by["s03"]["state"] == "done", by["s03"]
            assert by["s02"]["state"] == "faulted", by["s02"]
            m = re.search(r"no samples for ([\d.]+) s", by["s02"]["fault_reason"])
            assert m, by["s02"]["fault_reason"]
            assert stall_s <= float(m.group(1)) < stall_s + 1.0, by["s02"]["fault_reason"]
            assert status["state"] == "finished", status["error"]
            assert await coil(sim) is False


@pytest.mark.timeout(240)
async def test_writes_slower_than_the_stall_timeout_are_not_a_silent_board(tmp_path):
    """Two lost replies make s01's programming take two reply timeouts (2 x 0.5 s) on top of the
    drain before the writes: longer than the 1.0 s stall timeout while its stream is stopped. The
    write succeeds on its third attempt, and the part is verified."""
    async with SimStation(n_serial=2, n_can=0, seed=6, speed=SPEED) as sim:
        async with daemon(sim, tmp_path, SPEED, timing={"stall_timeout_s": 1.0}) as st:
            sim.board(0).cal.drop_replies(2)
            bid = st.start_batch("fast-thermal-verified", None, "pytest")
            status = await st.wait_batch(bid, timeout_s=220)
            by = {s["slot"]: s for s in status["slots"]}
            s01 = by["s01"]
            assert s01["state"] == "done", s01
            pv = s01["program"]
            assert pv["programmed"] is True and pv["attempts"] == 3 and len(pv["retries"]) == 2, pv
            assert all("no_reply" in r for r in pv["retries"]), pv["retries"]
            assert s01["verification"]["passed"] is True, s01["verification"]
            assert sim.board(0).cal.dropped_done == 2
            assert by["s02"]["state"] == "done", by["s02"]
            assert status["state"] == "finished", status["error"]
