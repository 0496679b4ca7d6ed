"""A DUT's broken temperature sensor faults that DUT quickly; the plate's lamp is never held (or
tripped) for one DUT (issue 36, part 3).

The pure core (station/daemon/temp_watch.py) on synthetic arrays and on the simulator's own healthy
output (whole fast-thermal runs, with links that lag, with and without peers and the reference
thermometer: never a finding); then the daemon with real parts (boards on ptys and an slcan pty,
the pymodbus lamp relay, SQLite on disk): one DUT's sensor stuck at the lamp's switch-on is faulted
with "temperature sensor" while the heat step and the batch go on, and a sensor that jumps to 91 C
faults its DUT without tripping the lamp for the plate.
"""

from __future__ import annotations

import asyncio
import re

import numpy as np
import pytest

from drivers.sim.physics import draw_population
from drivers.sim.profiles import fast_thermal_steps, run_steps
from drivers.sim.station_sim import SimStation
from drivers.sim.world import SimWorld
from station.daemon import temp_watch as tw
from station.daemon.temp_watch import TempWatch

ODR = 3.125


# ---------------------------------------------------------------------------------------- helpers
def die_rise_c(since_on_s, gain=1.0, die_tau_s=90.0, plate_tau_s=480.0, rise_c=32.0):
    """The die's rise after the lamp went on (plate first order, die first order behind it)."""
    t = np.maximum(np.asarray(since_on_s, dtype=float), 0.0)
    a, b = plate_tau_s, die_tau_s
    return rise_c * gain * (1.0 - (a * np.exp(-t / a) - b * np.exp(-t / b)) / (a - b))


def lis(x):
    """LIS3DSH temperature: 1 C counts."""
    return np.rint(x)


def run_blocks(watches, temps, lamp, t, block_n=16, plate=None, on_finding=None):
    """Feed every DUT's samples in blocks of block_n, DUT after DUT, each seeing the others as
    peers; the lamp flag of a block is the lamp at its last sample. Returns {index: finding}."""
    found = {}
    for a in range(0, t.size, block_n):
        b = min(a + block_n, t.size)
        for i, w in enumerate(watches):
            if i in found:
                continue
            peers = [p for k, p in enumerate(watches) if k != i and k not in found]
            f = w.update(t[a:b], temps[i][a:b], lamp_on=bool(lamp[b - 1]), peers=peers,
                         plate_temp_c=None if plate is None else float(plate[b - 1]))
            if f is not None:
                found[i] = f
                if on_finding is not None:
                    on_finding(i, f)
    return found


def heating(n_duts=4, off_s=600.0, on_s=1500.0, stuck=None, quant=lis, seed=0):
    """Lamp off off_s (ambient 24 C), then on on_s; DUT `stuck` reads its value at the switch-on."""
    t = np.arange(0.0, off_s + on_s, 1.0 / ODR)
    lamp = t >= off_s
    rng = np.random.default_rng(seed)
    temps = []
    for i in range(n_duts):
        x = 24.2 + die_rise_c(t - off_s, gain=1.0 + 0.03 * (i - 1.5), die_tau_s=60.0 + 20 * i)
        x = quant(x + rng.normal(0.0, 0.3, t.size))
        if i == stuck:
            x = np.where(t >= off_s, x[np.searchsorted(t, off_s) - 1], x)
        temps.append(x)
    return t, lamp, temps


# ---------------------------------------------------------------------------------------- stuck
def test_stuck_sensor_is_found_against_its_peers_in_about_three_minutes():
    t, lamp, temps = heating(stuck=2)
    found = run_blocks([TempWatch() for _ in temps], temps, lamp, t)
    assert list(found) == [2], found
    f = found[2]
    assert f.kind == "stuck"
    assert re.fullmatch(r"temperature sensor stuck at 24 C: the plate's other DUTs rose \d+\.\d C \(median\) "
                        r"in the \d+ s since the lamp went on", f.reason), f.reason
    since = f.time_s - 600.0
    assert tw.STUCK_MIN_S <= since <= 240.0, since
    rose = float(re.search(r"rose (\d+\.\d) C", f.reason).group(1))
    assert tw.STUCK_PEER_RISE_C <= rose < 9.0, f.reason


def test_a_healthy_dut_is_never_stuck_sitting_on_one_count_lagging_or_at_the_hot_plateau():
    """One LIS3DSH count for its first 100 s of heating (a slow die); a DUT 5 % less heated with the
    slowest die; the lamp on for an hour (the hot plateau: flat); then off for an hour: nothing."""
    t = np.arange(0.0, 600.0 + 3600.0 + 3600.0, 1.0 / ODR)
    lamp = (t >= 600.0) & (t < 4200.0)
    since = t - 600.0
    fast = 24.0 + die_rise_c(since, gain=1.05, die_tau_s=60.0)
    slow = 24.0 + die_rise_c(since, gain=0.95, die_tau_s=120.0)
    off = t >= 4200.0
    cool = lambda x: np.where(off, 24.0 + (x[np.searchsorted(t, 4200.0)] - 24.0) * np.exp(-(t - 4200.0) / 480.0), x)
    sitting = np.where((since > 0) & (since < 100.0), 24.0, slow)
    temps = [lis(cool(fast)), lis(cool(fast + 0.4)), lis(cool(slow)), lis(cool(sitting))]
    assert run_blocks([TempWatch() for _ in temps], temps, lamp, t) == {}
    # the same plate with only the two slowest (one of them one count late): still nothing
    assert run_blocks([TempWatch() for _ in range(2)], temps[2:], lamp, t) == {}


def test_lamp_off_flat_is_never_stuck():
    t = np.arange(0.0, 4 * 3600.0, 1.0 / ODR)
    temps = [np.full(t.size, 24.0), np.full(t.size, 25.0)]
    assert run_blocks([TempWatch(), TempWatch()], temps, np.zeros(t.size, bool), t) == {}
    assert run_blocks([TempWatch()], temps[:1], np.zeros(t.size, bool), t) == {}


def test_batch_of_one_compares_with_the_reference_thermometer():
    t, lamp, temps = heating(n_duts=1, stuck=0)
    plate = 24.0 + 32.0 * (1.0 - np.exp(-np.maximum(t - 600.0, 0.0) / 480.0))
    found = run_blocks([TempWatch()], temps, lamp, t, plate=plate)
    assert found[0].kind == "stuck", found
    assert "the plate's reference thermometer rose" in found[0].reason, found[0].reason
    assert found[0].time_s - 600.0 <= 240.0
    # healthy with its thermometer: nothing
    t, lamp, temps = heating(n_duts=1)
    assert run_blocks([TempWatch()], temps, lamp, t, plate=plate) == {}


def test_batch_of_one_without_thermometer_needs_a_flat_reading_after_a_lamp_on_from_cool():
    t, lamp, temps = heating(n_duts=1, stuck=0, off_s=600.0)
    found = run_blocks([TempWatch()], temps, lamp, t)
    assert found[0].kind == "stuck"
    assert "not one count of change for" in found[0].reason, found[0].reason
    assert tw.STUCK_FLAT_S <= found[0].time_s - 600.0 <= tw.STUCK_FLAT_S + 10.0
    # the lamp had been off only 200 s (the plate may still be hot): not judged
    t, lamp, temps = heating(n_duts=1, stuck=0, off_s=200.0)
    assert run_blocks([TempWatch()], temps, lamp, t) == {}
    # healthy (LIS3DSH counts, ADXL355-like fine steps): nothing
    for quant in (lis, lambda x: np.rint(x * 9.05) / 9.05):
        t, lamp, temps = heating(n_duts=1, quant=quant)
        assert run_blocks([TempWatch()], temps, lamp, t) == {}


def test_a_stuck_sensor_on_a_lagging_link_is_still_found():
    """Its samples arrive 60 s of sample time behind the others (lag_s): found, from its own time."""
    t, lamp, temps = heating(stuck=0)
    watches = [TempWatch() for _ in temps]
    lag = [60.0, 0.0, 0.0, 0.0]
    done = [0] * 4
    found = None
    for now in np.arange(0.0, t[-1], 4.0):
        k_now = int(np.searchsorted(t, now, side="right")) - 1
        for i, w in enumerate(watches):
            b = int(np.searchsorted(t, now - lag[i], side="right"))
            if b > done[i]:
                f = w.update(t[done[i]:b], temps[i][done[i]:b], lamp_on=bool(lamp[k_now]), lag_s=lag[i],
                             peers=[p for p in watches if p is not w])
                assert f is None or i == 0, (i, f)
                found = found or f
                done[i] = b
        if found:
            break
    assert found is not None and found.kind == "stuck", found
    assert found.time_s - 600.0 <= 240.0, found


def test_a_lamp_already_on_at_the_first_sample_is_not_judged():
    """A resumed batch: the watch did not see the lamp go on, so it cannot know the rise."""
    t, lamp, temps = heating(stuck=1)
    k = np.searchsorted(t, 600.0) + 1
    found = run_blocks([TempWatch() for _ in temps], [x[k:] for x in temps], lamp[k:], t[k:])
    assert found == {}


# ---------------------------------------------------------------------------------------- implausible
def test_a_jump_is_implausible_and_not_believed_before_it_is_judged():
    t = np.arange(0.0, 60.0, 1.0 / ODR)
    x = np.full(t.size, 24.0)
    k = np.searchsorted(t, 30.0)
    x[k:] = 91.0
    w = TempWatch()
    trusted = []
    found = None
    for a in range(0, t.size):  # one sample per block (a real-time link)
        found = w.update(t[a:a + 1], x[a:a + 1], lamp_on=False)
        trusted.append(w.trusted_max_c)
        if found:
            break
    assert found is not None and found.kind == "implausible"
    assert found.reason == "temperature sensor implausible: 24 C -> 91 C in 0.3 s", found.reason
    assert found.time_s - t[k] <= 1.0  # the 2nd sample at 91 C (the median of 3)
    assert all(v is None or v <= 24.0 for v in trusted), trusted  # 91 C was never shown to the lamp guard


def test_one_odd_sample_and_one_count_steps_are_not_implausible():
    t = np.arange(0.0, 120.0, 1.0 / ODR)
    x = np.where(np.arange(t.size) % 2 == 0, 24.0, 25.0)  # a LIS3DSH toggling one count every sample
    x[100] = 91.0  # one odd sample
    x[200] = -60.0
    w = TempWatch()
    seen = []
    for a in range(0, t.size, 5):
        assert w.update(t[a:a + 5], x[a:a + 5], lamp_on=False) is None
        seen.append(w.trusted_max_c)
    assert max(v for v in seen if v is not None) == 25.0


def test_out_of_range_and_a_fast_ramp_are_implausible_a_gradual_over_temperature_is_believed():
    t = np.arange(0.0, 60.0, 1.0 / ODR)
    w = TempWatch()
    f = w.update(t, np.full(t.size, 150.0), lamp_on=True)
    assert f is not None and f.reason == "temperature sensor implausible: reads 150 C, outside its -40..125 C range"
    assert w.trusted_max_c is None
    # 3 C/s for 10 s: beyond any lamp
    x = np.where(t < 20.0, 24.0, np.minimum(24.0 + 3.0 * (t - 20.0), 54.0))
    f = TempWatch().update(t, x, lamp_on=True)
    assert f is not None and f.kind == "implausible", f
    assert re.fullmatch(r"temperature sensor implausible: 2\d C -> \d\d(\.\d)? C in [2-5]\.\d s", f.reason), f.reason
    # a plate overheating at 0.2 C/s (2.5x the simulated lamp's fastest) up to 95 C: believed, so
    # the over-temperature check still sees it
    t = np.arange(0.0, 400.0, 1.0 / ODR)
    x = lis(24.0 + 0.2 * t)
    w = TempWatch()
    hottest = []
    for a in range(0, t.size, 10):
        assert w.update(t[a:a + 10], x[a:a + 10], lamp_on=True) is None
        hottest.append(w.trusted_max_c)
    assert hottest[-1] == x[-1] > 85.0


def test_a_gap_in_the_samples_is_no_jump_but_a_jump_after_it_still_is():
    """Samples lost (the link's, or the station's backlog): the plate heated 17 C while none came.
    No rate is measured across the gap, so the sensor is not blamed; a real jump after it still is."""
    t = np.arange(0.0, 60.0, 1.0 / ODR)
    t2 = 3000.0 + np.arange(0.0, 60.0, 1.0 / ODR)  # 49 min of samples lost
    w = TempWatch()
    assert w.update(t, np.full(t.size, 30.0), lamp_on=True) is None
    for a in range(0, t2.size, 4):
        assert w.update(t2[a:a + 4], np.full(min(4, t2.size - a), 47.0), lamp_on=True) is None
    t3 = t2[-1] + np.arange(1, 40) / ODR
    found = None
    for a in range(0, t3.size, 2):
        found = found or w.update(t3[a:a + 2], np.full(min(2, t3.size - a), 80.0), lamp_on=True)
    assert found is not None and found.kind == "implausible" and "47 C -> 80 C" in found.reason, found


# ---------------------------------------------------------------------------------------- simulator, healthy
def _sim_run(seed):
    truths = (draw_population(5, seed, sensor="LIS3DSH")
              + draw_population(3, seed + 1, sensor="ADXL355", serial_prefix="ADX"))
    world = SimWorld(truths, seed=seed)
    cols = run_steps(world, fast_thermal_steps())
    temps = [world.identity(i).temp_c(cols["temp_counts"][i]) for i in range(len(truths))]
    return cols, temps


@pytest.mark.parametrize("seed", [3, 8])
def test_the_simulators_healthy_fast_thermal_runs_give_no_finding(seed):
    """Whole fast-thermal runs (P ambient, P hot, N hot with the plate hotter over the lamp, the hot
    plateau, N ambient) of 8 DUTs, both sensor kinds: no finding with peers, with the reference
    thermometer alone, alone; with links that lag 30 and 90 s of sample time behind the others (the
    lamp flag and the thermometer are read when the block arrives); every reading believed."""
    cols, temps = _sim_run(seed)
    t, lamp, plate = cols["time_s"], cols["lamp"].astype(bool), cols["plate_temp_c"]
    n = len(temps)
    assert run_blocks([TempWatch() for _ in range(n)], temps, lamp, t, plate=plate) == {}
    for i in (0, 5):  # one LIS3DSH, one ADXL355
        assert run_blocks([TempWatch()], [temps[i]], lamp, t, plate=plate) == {}
        assert run_blocks([TempWatch()], [temps[i]], lamp, t) == {}
    lag_s = np.zeros(n)
    lag_s[2], lag_s[6] = 30.0, 90.0
    watches = [TempWatch() for _ in range(n)]
    done = np.zeros(n, dtype=int)
    for now in np.arange(0.0, t[-1] + 100.0, 4.0):  # the station reads every 4 s of sample time
        k_now = min(int(np.searchsorted(t, now, side="right")), t.size) - 1
        for i, w in enumerate(watches):
            b = int(np.searchsorted(t, now - lag_s[i], side="right"))
            if b <= done[i]:
                continue
            f = w.update(t[done[i]:b], temps[i][done[i]:b], lamp_on=bool(lamp[k_now]), lag_s=lag_s[i],
                         peers=[p for p in watches if p is not w], plate_temp_c=float(plate[k_now]))
            assert f is None, (i, f)
            assert w.trusted_max_c == float(np.max(temps[i][done[i]:b]))
            done[i] = b


def test_the_simulator_sticks_and_fakes_a_sensor_in_the_counts_every_board_sends():
    truths = draw_population(2, 1, sensor="LIS3DSH") + draw_population(1, 1, sensor="ADXL355", serial_prefix="A")
    w = SimWorld(truths, seed=1)
    w.advance(100)
    w.lamp_on = True
    first = w.advance(50)
    w.stick_temp_sensor(0)
    w.temp_sensor_reads(2, 91.0, from_s=w.time_s + 10.0)
    c = w.advance(2000)
    assert np.all(c.temp_counts[0] == first.temp_counts[0][-1])  # stuck at its reading before
    assert np.ptp(c.die_temp_c[0]) > 5.0  # while the die heats
    assert np.ptp(c.temp_counts[1]) >= 5  # the others heat
    ident = w.identity(2)
    k = int(np.searchsorted(c.time_s, c.time_s[0] + 10.0 - 1e-9))
    assert np.allclose(ident.temp_c(c.temp_counts[2][k:]), 91.0, atol=0.06)
    assert abs(ident.temp_c(c.temp_counts[2][:k]) - c.die_temp_c[2][:k]).max() < 1.0
    w.heal_temp_sensor(0)
    assert np.ptp(w.advance(500).temp_counts[0]) >= 1


# ---------------------------------------------------------------------------------------- the daemon
def _stick_at_lamp_on(sim, i):
    """Arm DUT i's sensor to stick at the lamp's switch-on (at its reading then); returns a dict
    that gets the world's lamp-on sample time."""
    seen: dict = {}

    def on_chunk(chunk):
        if chunk.lamp_on and "lamp_on_s" not in seen:
            seen["lamp_on_s"] = float(chunk.time_s[0])
            sim.world.stick_temp_sensor(i)

    sim.subscribe(on_chunk)
    return seen


async def _run_fast_thermal(tmp_path, stuck: int | None, speed: float = 150.0):
    from test_daemon_e2e import coil, daemon

    async with SimStation(n_serial=3, n_can=1, seed=12, speed=speed) as sim:
        seen = _stick_at_lamp_on(sim, stuck) if stuck is not None else {}
        async with daemon(sim, tmp_path, speed) as st:
            events = st.bus.subscribe(maxsize=1_000_000)
            bid = st.start_batch("fast-thermal", None, "pytest")
            status = await st.wait_batch(bid, timeout_s=200)
            windows = {}
            while not events.empty():
                e = events.get_nowait()
                if e.kind == "StepCompleted":
                    windows[e.step_index] = e.windows
            await st.flush_db()
            from db.repository import results_since

            feed = await asyncio.to_thread(results_since, st.db, 0, 1000)
            assert await coil(sim) is False
            # sample time from the world's lamp-on to the finding (a serial board's clock is the world's)
            found_after = {d.slot: d.temp_watch.finding.time_s - seen["lamp_on_s"]
                           for d in st.batches[bid].duts if d.temp_watch.finding is not None}
            return status, windows, feed, found_after, [t.serial for t in sim.truths]


@pytest.mark.timeout(300)
async def test_a_stuck_sensor_faults_its_dut_and_the_heat_step_goes_on(tmp_path):
    """4 DUTs (3 serial, 1 CAN) run fast-thermal; s02's sensor sticks at the lamp's switch-on.
    s02 is faulted with "temperature sensor stuck" within STUCK_BOUND_S of sample time after the
    lamp went on (measured: 151-164 s after the world's lamp-on; the reason says 158-167 s, from the
    daemon's own, earlier estimate); P hot ends when the 3 healthy DUTs have their hot segment, as
    long as in a healthy batch (measured with seed 12: 1440-1490 s of sample time with a DUT stuck,
    1442 s without, against the 3,000 s timeout the stuck sensor held it for before); the
    healthy DUTs are judged on their data; nothing of s02 reaches the MES as pass. On the old code
    s02 held P hot (and the lamp) for 3,000 s and was faulted "step 'P hot' timed out ... without a
    segment": this test fails there."""
    status, windows, feed, found_after, serials = await _run_fast_thermal(tmp_path, stuck=1)
    assert status["state"] == "finished", status["error"]
    by = {s["slot"]: s for s in status["slots"]}
    bad = by["s02"]
    assert bad["state"] == "faulted", bad
    reason = bad["fault_reason"]
    assert re.fullmatch(r"temperature sensor stuck at \d+ C: the plate's other DUTs rose \d+\.\d C \(median\) "
                        r"in the \d+ s since the lamp went on", reason), reason
    assert set(found_after) == {"s02"} and found_after["s02"] <= STUCK_BOUND_S, found_after
    assert bad["decision"]["verdict"] == "error", bad["decision"]
    for slot in ("s01", "s03", "c01"):
        s = by[slot]
        assert s["state"] == "done", s
        assert s["decision"]["verdict"] in ("pass", "marginal", "fail"), s["decision"]
        assert s["result"] is not None and s["result"]["axes"], s
    # P hot (step 1, the lamp on) lasted what the healthy DUTs need, not the 3,000 s timeout
    p_hot = {slot: b - a for slot, (a, b) in windows[1].items()}
    assert set(p_hot) == {"s01", "s03", "c01"}, p_hot
    assert max(p_hot.values()) < P_HOT_MAX_S, p_hot
    stuck_serial = serials[1]
    mes = [r for r in feed if r.get("serial") == stuck_serial]
    assert mes and all(r["verdict"] == "error" for r in mes), mes
    assert not any(r["verdict"] == "pass" for r in mes)


STUCK_BOUND_S = 300  # sample s after the lamp went on by which a stuck sensor among 3 healthy peers is faulted
P_HOT_MAX_S = 2000.0  # P hot's length (sample s) on the 3 healthy DUTs; a healthy batch: ~1440 s


@pytest.mark.timeout(120)
async def test_an_implausible_jump_faults_its_dut_and_does_not_trip_the_lamp(tmp_path):
    """The lamp on (lamp-test profile); s01's sensor jumps to 91 C, above the 85 C DUT limit: s01 is
    faulted "temperature sensor implausible", the lamp stays on for s02 and c01 (no safety trip),
    and the batch goes on until aborted. (A real, gradual over-temperature still trips the lamp:
    tests/test_daemon_e2e.py test_over_temperature_trips_lamp.)"""
    from test_daemon_e2e import LAMP_TEST_PROFILE, coil, daemon, wait_for

    speed = 100.0
    async with SimStation(n_serial=2, n_can=1, seed=3, speed=speed) as sim:
        async with daemon(sim, tmp_path, speed, profiles=LAMP_TEST_PROFILE) as st:
            alarms = st.bus.subscribe(maxsize=100000)
            bid = st.start_batch("lamp-test", None, "pytest")
            await wait_for(lambda: coil(sim), 30, "lamp coil on")
            await asyncio.sleep(1.0)  # 100 s of heating
            sim.world.temp_sensor_reads(0, 91.0)
            await wait_for(lambda: st.batch_status(bid)["slots"][0]["state"] == "faulted", 20, "s01 faulted")
            await asyncio.sleep(1.0)  # the lamp stays on while the others go on
            status = st.batch_status(bid)
            assert status["state"] not in ("failed", "aborted", "finished"), status["error"]
            by = {s["slot"]: s for s in status["slots"]}
            assert by["s01"]["fault_reason"].startswith("temperature sensor implausible: "), by["s01"]
            assert "-> 91 C in 0.3 s" in by["s01"]["fault_reason"], by["s01"]["fault_reason"]
            assert by["s02"]["state"] == "running" and by["c01"]["state"] == "running", by
            assert st.lamp.trip_reason is None and await coil(sim) is True
            st.abort(bid, reason="test done")
            await st.wait_batch(bid, timeout_s=10)
            texts = []
            while not alarms.empty():
                e = alarms.get_nowait()
                if e.kind == "Alarm":
                    texts.append(e.text)
            assert not any("safety trip" in t for t in texts), texts


def test_levels_kept_with_the_history_are_the_levels_of_the_history():
    """TempWatch keeps each sample's level (the median of LEVEL_N) with its history and computes a
    block's new samples only: what it keeps must be what the whole history gives (from the first
    sample with LEVEL_N before it), so the range, rate and trust rules see the same numbers."""
    from station.daemon.temp_watch import LEVEL_N, TempWatch, _levels

    rng = np.random.default_rng(3)
    w = TempWatch()
    t0 = 0.0
    for _ in range(300):
        n = int(rng.integers(1, 9))
        t = t0 + 0.32 * np.arange(1, n + 1)
        t0 = float(t[-1])
        w.update(t, 25.0 + np.round(rng.normal(0, 0.3, n), 1), lamp_on=False)
        ref = _levels(w._c)
        assert w._lev.size == w._c.size
        assert np.array_equal(w._lev[LEVEL_N - 1:], ref[LEVEL_N - 1:])
