"""station/science/placement.py: a sample is placed only where the DUT measures the position, settled.

Truth here is the simulated world's own gravity (drivers/sim/world.py turn_to): a plate turned over
seconds passes through other directions, and only samples after 5 s at the asked position count.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from contracts.positions import GRAVITY_DIRECTIONS, POSITION_INDEX, SFEM24
from drivers.sim.physics import draw_population
from drivers.sim.world import SimWorld
from station.science.placement import (
    PLACEMENT_SETTLE_S, Placement, direction_id, direction_ids, direction_name, label_cuts, same_direction,
)

P, N = POSITION_INDEX["P"], POSITION_INDEX["N"]


def _turn_record(noise_scale: float = 1.0):
    """A plate at N, turned to P over 4 s, then left: (t, acc of DUT 0, world gravity per sample)."""
    w = SimWorld(draw_population(1, 5), seed=5)
    w._noise = w._noise * noise_scale
    w.position = N
    parts, grav = [w.advance(40)], [np.tile(GRAVITY_DIRECTIONS[N], (40, 1))]
    w.turn_to(P, 4.0)
    for _ in range(80):
        grav.append(w.gravity()[None, :])
        parts.append(w.advance(1))
    t = np.concatenate([c.time_s for c in parts])
    acc = np.concatenate([c.acc_counts[0] for c in parts]) * w._lsb_g[0]
    return t, acc, np.concatenate(grav)


def test_a_turn_is_placed_only_after_it_settles_at_the_position():
    t, acc, grav = _turn_record()
    placed = Placement().placed(t, acc, P)
    at_p = np.flatnonzero(grav @ GRAVITY_DIRECTIONS[P] > np.cos(np.radians(1.0)))  # the plate really is at P
    first = int(np.flatnonzero(placed)[0])
    assert placed[first:].all(), "once settled, every later sample is placed"
    # the first placed sample comes settle_s after the DUT first faced P, never before the plate got there
    assert t[first] >= t[at_p[0]]
    assert t[first] - t[at_p[0]] <= PLACEMENT_SETTLE_S + 2.0 / 3.125
    assert not Placement().placed(t, acc, N)[first:].any()
    assert Placement().placed(t, acc, None).sum() == 0


@pytest.mark.parametrize("noise_scale", [0.4, 1.0, 3.0, 10.0])
def test_noisier_parts_are_still_placed(noise_scale):
    t, acc, _ = _turn_record(noise_scale)
    p = Placement()
    placed = p.placed(t, acc, P)
    assert placed[-20:].all(), noise_scale
    assert p.settled_direction() == direction_id(P)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(min_value=1, max_value=60), min_size=1, max_size=20))
def test_labels_do_not_depend_on_how_the_stream_is_cut(cuts):
    t, acc, _ = _turn_record()
    whole = Placement().placed(t, acc, P)
    p, parts, k = Placement(), [], 0
    for c in cuts + [len(t)]:
        parts.append(p.placed(t[k:k + c], acc[k:k + c], P))
        k += c
        if k >= len(t):
            break
    assert np.array_equal(np.concatenate(parts)[:len(t)], whole)


def test_directions_and_words():
    assert direction_name(direction_id(P)) == "P" and direction_name(direction_id(N)) == "N"
    assert same_direction(POSITION_INDEX["sfem-z0"], POSITION_INDEX["+x"])  # the same way up
    assert not same_direction(POSITION_INDEX["sfem-z0"], POSITION_INDEX["sfem-z45"])
    # 45 deg apart: each sfem-24 position is told from its neighbours, a between-direction from both
    for name in SFEM24:
        assert direction_ids(GRAVITY_DIRECTIONS[POSITION_INDEX[name]][None, :])[0] == direction_id(POSITION_INDEX[name])
    mid = GRAVITY_DIRECTIONS[P] + GRAVITY_DIRECTIONS[POSITION_INDEX["+x"]]
    assert direction_ids(mid[None, :])[0] == -1
    assert label_cuts(np.array([-1, 0, 0, -1, 1])) == [(0, 1), (1, 3), (3, 4), (4, 5)]
