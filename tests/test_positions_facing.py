"""contracts.positions.first_facing: a static step starts at the first sample that shows its position."""

import numpy as np

from contracts.positions import SFEM24, direction, first_facing


def test_first_facing_skips_the_previous_position_and_motion():
    prev, new = direction(SFEM24[0]), direction(SFEM24[1])  # 45 deg apart
    mid = (prev + new) / np.linalg.norm(prev + new)  # 22.5 deg from each: still moving
    acc = np.vstack([np.tile(prev, (5, 1)), np.tile(mid, (3, 1)), np.tile(new * 1.02, (4, 1))])
    assert first_facing(acc, SFEM24[1]) == 8
    assert first_facing(acc[:8], SFEM24[1]) is None
    assert first_facing(np.zeros((0, 3)), SFEM24[1]) is None


def test_a_few_degrees_of_mounting_and_scale_error_still_face():
    rng = np.random.default_rng(1)
    for name in SFEM24 + ["P", "N", "+x", "-z"]:
        a = np.radians(rng.uniform(-5, 5, 3))
        rz = np.array([[np.cos(a[2]), -np.sin(a[2]), 0], [np.sin(a[2]), np.cos(a[2]), 0], [0, 0, 1]])
        ry = np.array([[np.cos(a[1]), 0, np.sin(a[1])], [0, 1, 0], [-np.sin(a[1]), 0, np.cos(a[1])]])
        g = np.diag([1.03, 0.97, 1.01]) @ rz @ ry @ direction(name) + rng.normal(0, 2e-3, 3)
        assert first_facing(g[None, :], name) == 0, name
        assert first_facing(-g[None, :], name) is None, name  # upside down never faces
