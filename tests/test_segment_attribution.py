"""A segment the calibrator logs while the plate's position is unknown must not end the batch.

Seen in CI under load (x600): boards connect and the first positioning takes longer, in sample
time, than a segment needs (~554 s); the streaming calibrator saved its ambient segment while the
sequencer did not know where the plate was, no step could use it, and the calibrator waited for
a temperature or orientation change that never came: "step 'P ambient' timed out after 1800 s
sample time without a segment". Here a fixture that takes 700 sample seconds to confirm every move
(even to where it already is) makes that happen every time, without load.
"""

from __future__ import annotations

import pytest

from drivers.sim.station_sim import SimStation
from cli.commands.demo import sim_config
from station.config import parse_config
from station.daemon.storage import open_database
from station.daemon.supervisor import Station

SPEED = 600.0


@pytest.mark.timeout(240)
async def test_a_segment_logged_during_a_slow_first_positioning_is_logged_again(tmp_path):
    async with SimStation(n_serial=2, seed=5, speed=SPEED) as sim:
        assert sim.modbus is not None
        sim.modbus.settle_s = 700.0  # > the ~554 s a segment needs at 3.125 Hz
        cfg = parse_config(sim_config(sim, speed=SPEED, db_url=f"sqlite:///{tmp_path / 's.db'}"), "<test>")
        db = open_database(cfg.database_url)
        st = Station(cfg, db=db)
        await st.start()
        try:
            bid = st.start_batch("fast-thermal", None, "pytest")
            status = await st.wait_batch(bid, timeout_s=200)
            assert status["state"] == "finished", status["error"]
            for s in status["slots"]:
                assert s["state"] == "done", s["fault_reason"]
                axes = s["result"]["axes"]
                truth = sim.truths[int(s["slot"][1:]) - 1]
                for k, ax in enumerate("xyz"):  # the re-logged segments give the right answer
                    assert axes[ax]["tdb_mg_per_c"] == pytest.approx(truth.tdb_mg_per_c[k], abs=0.03)
        finally:
            await st.close("test end")
            db.dispose()
