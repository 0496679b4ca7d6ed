"""Streaming calibrator (martinez2022 3.3): segments, counts, gate, changes, result, and
bit-identity of the one-sample and batch paths wherever the batches are cut."""

import numpy as np
import pytest

from station.science.drift_coefficients import InsufficientData
from station.science.streaming import StreamingCalibrator
from station.science.streaming_config import StreamingConfig
from contracts.types import StationError
from thermal_synth import fast_thermal

TABLE6 = [  # martinez2022 Table 6, proposed technique: (TDB mg/C, TDSF ppm/C) per axis
    ((0.47, 0.07, -0.20), (-125.0, -38.0, 0.0)),
    ((1.30, 0.34, -0.88), (-113.0, 0.0, -96.0)),
    ((-0.92, -0.07, 0.16), (-167.0, -35.0, 0.0)),
    ((0.29, 0.22, -0.84), (0.0, -200.0, -496.0)),
]


def _run_batch(rec, config=None):
    cal = StreamingCalibrator(config)
    segs = cal.update_batch(rec.time_s, rec.acc_g, rec.temp_c)
    assert segs == cal.segments
    return cal


@pytest.mark.parametrize("case", range(4))
def test_recovers_truth_on_fast_thermal_record(case):
    tdb, tdsf = TABLE6[case]
    rec = fast_thermal(seed=case, tdb_mg_per_c=tdb, tdsf_ppm_per_c=tdsf)
    cal = _run_batch(rec)
    segs = cal.segments
    assert [s.orientation for s in segs] == [0, 0, 1, 1]
    assert all(s.n_samples == 1000 for s in segs)
    # P ambient, P hot, N hot, N ambient: the segments sit in their phases
    phase = np.searchsorted(rec.phase_starts_s, [s.t_start_s for s in segs], side="right") - 1
    assert list(phase) == [0, 1, 2, 3]
    assert segs[1].temp_mean_c - segs[0].temp_mean_c > 20 and segs[2].temp_mean_c - segs[3].temp_mean_c > 20
    assert np.all(np.array(segs[0].acc_mean_g) > 0.5) and np.all(np.array(segs[2].acc_mean_g) < -0.5)
    res = cal.result()
    assert res.method == "streaming" and res.n_segments == 4
    for k, ax in enumerate("xyz"):
        a = res.axes[ax]
        assert abs(a.tdb_mg_per_c - tdb[k]) < 0.03, (ax, a)
        assert abs(a.tdsf_ppm_per_c - tdsf[k]) < 40.0, (ax, a)
        assert a.tdsf_ppm_per_c <= 0.0
        assert a.tdb_sigma_mg_per_c is None
        # Table 2 per axis: TD_i and Acc0_i of both orientations, consistent with eq. 2
        tds = {o.orientation: o for o in res.orientations[ax]}
        for o in (0, 1):
            td_true = tdb[k] + tdsf[k] * 1e-3 * tds[o].acc0_g
            assert abs(tds[o].td_mg_per_c - td_true) < 0.02


def _scalar_trace(rec, config=None):
    cal = StreamingCalibrator(config)
    segs, states, grads, orients, done_at = [], [], [], [], []
    for i in range(rec.time_s.shape[0]):
        new = cal.update(rec.time_s[i], rec.acc_g[i], rec.temp_c[i])
        segs += new
        if new:
            done_at.append(i)
        states.append(cal.state)
        grads.append(cal.gradient_c_per_min)
        orients.append(cal.orientation)
    return cal, segs, states, grads, orients, done_at


def _check_identity(rec, config, rng):
    cal_s, segs_s, states, grads, orients, done_at = _scalar_trace(rec, config)
    assert len(segs_s) >= 4
    n = rec.time_s.shape[0]
    # awkward cuts: at, just before and just after every state change and every completed segment,
    # plus random ones, plus runs of one-sample batches around the turn
    changes = [i for i in range(1, n) if states[i] != states[i - 1] or orients[i] != orients[i - 1]]
    cuts = set()
    for i in changes + done_at:
        cuts.update((i - 1, i, i + 1, i + 2))
    cuts.update(rng.integers(1, n, 40).tolist())
    turn = int(np.argmax(rec.position == -1))
    cuts.update(range(turn - 30, turn + 60))
    cuts = sorted(c for c in cuts if 0 < c < n)
    cal_b = StreamingCalibrator(config)
    segs_b = []
    prev = 0
    for c in cuts + [n]:
        segs_b += cal_b.update_batch(rec.time_s[prev:c], rec.acc_g[prev:c], rec.temp_c[prev:c])
        # the whole state matches the one-sample path at every cut
        assert cal_b.state == states[c - 1], c
        assert cal_b.gradient_c_per_min == grads[c - 1], c
        assert cal_b.orientation == orients[c - 1], c
        assert cal_b.samples_seen == c
        prev = c
    assert segs_b == segs_s  # same segments, same sample indices (times), same numbers to the bit
    assert cal_b.__dict__.keys() == cal_s.__dict__.keys()
    for key in ("_facc", "_ftemp", "_grad", "_n_disc", "_n_avg", "_orientation", "_last_acc", "_last_temp"):
        assert getattr(cal_b, key) == getattr(cal_s, key), key
    # and in one single batch
    cal_1 = StreamingCalibrator(config)
    assert cal_1.update_batch(rec.time_s, rec.acc_g, rec.temp_c) == segs_s
    r_s, r_b = cal_s.result().to_json(), cal_b.result().to_json()
    assert r_s == r_b


def test_scalar_and_batch_paths_are_bit_identical():
    rec = fast_thermal(seed=11, tdb_mg_per_c=(1.3, 0.34, -0.88), tdsf_ppm_per_c=(-113, 0, -96))
    _check_identity(rec, None, np.random.default_rng(0))


def test_bit_identity_with_other_constants_and_bad_timestamps():
    rec = fast_thermal(seed=5, extra_steps=1)
    # duplicated and backwards timestamps contribute a zero gradient in both paths
    rec.time_s[1000] = rec.time_s[999]
    rec.time_s[3000:3003] = rec.time_s[2990]
    cfg = StreamingConfig(discard_samples=0, average_samples=333, gradient_reset_c_per_min=25.0,
                          detect_orientation_while_logging=False, alpha_acc=0.1)
    _check_identity(rec, cfg, np.random.default_rng(1))


def test_random_batch_sizes_same_segments():
    rec = fast_thermal(seed=3)
    ref = _run_batch(rec).segments
    rng = np.random.default_rng(7)
    cal = StreamingCalibrator()
    i, out = 0, []
    while i < rec.time_s.shape[0]:
        k = int(rng.choice([1, 2, 3, 7, 64, 499, 500, 501, 1000, 1499, 4096]))
        out += cal.update_batch(rec.time_s[i : i + k], rec.acc_g[i : i + k], rec.temp_c[i : i + k])
        i += k
    assert out == ref


def _constant(n, temp=25.0, acc=(0.577, 0.577, 0.577)):
    t = np.arange(n) / 3.125
    return t, np.tile(np.asarray(acc), (n, 1)), np.full(n, temp)


def _first_open(reset=10.0, alpha_g=0.01):
    g, k = reset, 0
    while not abs(g) < 1.0:
        k += 1
        g = g * (1.0 - alpha_g) + alpha_g * 0.0
    return k


@pytest.mark.parametrize("discard, average", [(500, 1000), (100, 50), (0, 10)])
def test_discard_then_average_counts_exactly(discard, average):
    t, acc, temp = _constant(5000)
    cfg = StreamingConfig(discard_samples=discard, average_samples=average)
    cal = StreamingCalibrator(cfg)
    segs = cal.update_batch(t, acc, temp)
    assert len(segs) == 1  # then it waits: nothing changes
    k0 = _first_open()  # the gradient starts at the reset value and decays with alpha 0.01
    s = segs[0]
    assert s.n_samples == average
    assert s.t_start_s == t[k0 + discard] and s.t_end_s == t[k0 + discard + average - 1]
    assert s.acc_mean_g == pytest.approx((0.577,) * 3, abs=1e-15) and s.acc_std_g == pytest.approx((0, 0, 0), abs=1e-9)
    assert cal.state == "waiting"


def test_gate_closing_restarts_discard_and_average():
    n = 8000
    t, acc, temp = _constant(n)
    k0 = _first_open()
    # a 4 C bump (no segment change) during averaging: +4 C in 30 s and back 3 min later
    i0 = k0 + 500 + 300
    bump = np.interp(np.arange(n), [i0, i0 + 94, i0 + 660, i0 + 754], [0, 4, 4, 0])
    temp = temp + bump
    cal = StreamingCalibrator()
    segs = cal.update_batch(t, acc, temp)
    assert len(segs) == 1
    s = segs[0]
    assert s.t_start_s > t[i0 + 754] + 500 / 3.125  # after the bump, 500 more discarded samples
    assert s.temp_mean_c == 25.0
    # the single-sample path agrees
    cal2 = StreamingCalibrator()
    out = [seg for i in range(n) for seg in cal2.update(t[i], acc[i], temp[i])]
    assert out == segs


def test_temperature_and_orientation_changes():
    # P at 25 C, then +25 C (segment change), then turned (orientation change), then back to 25 C
    parts = [(4000, 25.0, 0.577), (4000, 50.0, 0.577), (4000, 50.0, -0.577), (4000, 25.0, -0.577)]
    t = np.arange(16000) / 3.125
    acc = np.concatenate([np.full((k, 3), a) for k, _, a in parts])
    temp = np.concatenate([np.full(k, c) for k, c, _ in parts])
    cal = StreamingCalibrator()
    segs = cal.update_batch(t, acc, temp)
    assert [(s.orientation, s.temp_mean_c) for s in segs] == [(0, 25.0), (0, 50.0), (1, 50.0), (1, 25.0)]
    # each new segment starts after the change plus the gradient reset decay plus 500 discards
    k0 = _first_open()
    for j, s in enumerate(segs[1:], start=1):
        assert s.t_start_s >= t[4000 * j + k0 + 500 - 25]
    # a 15 C change (< 20 C) is no new segment
    temp2 = np.where(np.arange(16000) >= 4000, 40.0, 25.0)
    assert len(StreamingCalibrator().update_batch(t, np.full((16000, 3), 0.577), temp2)) == 1
    # orientation change needs ALL axes to move more than 0.8 g
    acc3 = np.full((16000, 3), 0.577)
    acc3[4000:, :2] = -0.577
    assert len(StreamingCalibrator().update_batch(t, acc3, np.full(16000, 25.0))) == 1


def test_orientation_change_before_a_segment_completes():
    # turned while the hot segment is still settling: detected (default) or mixed (paper-strict)
    n1, n2, n3 = 4000, 400, 4000
    t = np.arange(n1 + n2 + n3) / 3.125
    acc = np.concatenate([np.full((n1 + n2, 3), 0.577), np.full((n3, 3), -0.577)])
    temp = np.concatenate([np.full(n1, 25.0), np.full(n2 + n3, 50.0)])
    segs = StreamingCalibrator().update_batch(t, acc, temp)
    assert [s.orientation for s in segs] == [0, 1]
    strict = StreamingCalibrator(StreamingConfig(detect_orientation_while_logging=False)).update_batch(t, acc, temp)
    assert [s.orientation for s in strict] == [0, 0]


def test_positive_tdsf_is_clamped_and_flagged():
    rec = fast_thermal(seed=2, tdb_mg_per_c=(0.5, 0.5, 0.5), tdsf_ppm_per_c=(300.0, -200.0, 0.0))
    res = _run_batch(rec).result()
    assert res.axes["x"].tdsf_clamped and res.axes["x"].tdsf_ppm_per_c == 0.0
    assert not res.axes["y"].tdsf_clamped and abs(res.axes["y"].tdsf_ppm_per_c + 200) < 40
    assert abs(res.axes["x"].tdb_mg_per_c - 0.5) < 0.03
    unclamped = _run_batch(rec, StreamingConfig(clamp_positive_tdsf=False)).result()
    assert abs(unclamped.axes["x"].tdsf_ppm_per_c - 300) < 40 and not unclamped.axes["x"].tdsf_clamped


def test_more_than_two_temperature_segments_per_orientation():
    rec = fast_thermal(seed=4, extra_steps=1, tdb_mg_per_c=(-0.92, -0.07, 0.16), tdsf_ppm_per_c=(-167, -35, -60))
    cal = _run_batch(rec)
    assert [s.orientation for s in cal.segments] == [0, 0, 1, 1, 1, 1]
    res = cal.result()
    for k, ax in enumerate("xyz"):
        assert abs(res.axes[ax].tdb_mg_per_c - rec.truth.tdb_mg_per_c[k]) < 0.03
        assert abs(res.axes[ax].tdsf_ppm_per_c - rec.truth.tdsf_ppm_per_c[k]) < 40


def test_needs_two_segments_in_two_orientations():
    rec = fast_thermal(seed=1, phases_min=(25.0, 30.0, 0.5, 0.5))  # never logs in N
    cal = _run_batch(rec)
    assert [s.orientation for s in cal.segments] == [0, 0]
    with pytest.raises(InsufficientData) as err:
        cal.result()
    assert isinstance(err.value, StationError) and "two orientations" in str(err.value)
    # a larger required temperature change leaves one segment per orientation
    cal = _run_batch(fast_thermal(seed=1), StreamingConfig(segment_delta_c=40.0))
    with pytest.raises(InsufficientData):
        cal.result()
