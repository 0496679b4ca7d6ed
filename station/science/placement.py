"""Where a DUT is, from what it measures: the placement of each sample (docs/design.md section 4).

The station never labels a sample by a button or a fixture's "reached" bit alone: a person presses
Done before turning the plate, turns it over seconds, pauses for minutes, turns it to the wrong
position or back; a fixture reports "reached" before the plate has stopped; in compressed time the
boards' bytes lag the plant by seconds. What the DUT measures is the truth: its static reading is
gravity, a unit vector in its own frame, and every named position has its nominal direction
(contracts/positions.py).

Rule (one per sample, causal, so a live stream, a replay and a stored log give the same labels):
- a sample FACES a named position when its measured gravity points within `max_angle_deg`
  (contracts.positions.FACING_MAX_ANGLE_DEG, 20 deg: under half the 45 deg between neighbouring
  sfem-24 positions, far above a few degrees of mounting error and the noise of any part);
- a DUT is SETTLED at a position when every sample of the last `settle_s` of sample time faced it
  (PLACEMENT_SETTLE_S, 5 s): a plate being turned, put down or bumped is not;
- a sample is PLACED at a position the station accepts when the DUT is settled there at that
  sample: the step's own, the previous step's until the DUT has arrived at the new one, and the
  next step's (station/daemon/intake.place; `sequence_labels` walks a whole record the same way).
The station then stores that position for placed samples and -1 for every other, feeds the
streaming calibrator only placed samples (its averaging window starts over after every gap) and
fits only placed samples (station/science/thermal_calibration.py drops -1 rows too).

Pure: arrays in, labels out; `Placement` carries only the current run between blocks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from contracts.positions import FACING_MAX_ANGLE_DEG, GRAVITY_DIRECTIONS, POSITION_NAMES

PLACEMENT_SETTLE_S = 5.0  # sample seconds a DUT must face a position, without a break, to be placed there
_ROWS_PER_CHUNK = 1 << 16  # samples whose direction cosines are held at once (direction_ids)


def _unique_directions() -> tuple[np.ndarray, np.ndarray]:
    """Distinct nominal directions (some sfem-24 positions point where a six-position one does:
    sfem-z0 is +x) and, per position index, the index of its direction among them."""
    uniq: list[np.ndarray] = []
    canon = np.empty(len(GRAVITY_DIRECTIONS), dtype=np.int64)
    for i, v in enumerate(GRAVITY_DIRECTIONS):
        for j, u in enumerate(uniq):
            if float(u @ v) > 1.0 - 1e-9:
                canon[i] = j
                break
        else:
            canon[i] = len(uniq)
            uniq.append(v)
    return np.array(uniq), canon


_DIRS, _CANON = _unique_directions()
# The name a direction is called by in words: the first position that has it (P, N, +x, ...).
_DIR_NAME = [POSITION_NAMES[int(np.flatnonzero(_CANON == j)[0])] for j in range(len(_DIRS))]


def direction_ids(acc_g: np.ndarray, max_angle_deg: float = FACING_MAX_ANGLE_DEG) -> np.ndarray:
    """Per sample, the id of the named direction its gravity points at within max_angle_deg, or -1
    (between positions, or a reading that is not 1 g of gravity alone)."""
    acc = np.asarray(acc_g, dtype=np.float64).reshape(-1, 3)
    n = acc.shape[0]
    out = np.empty(n, dtype=np.int64)
    limit = math.cos(math.radians(max_angle_deg))
    # in chunks: the cosines against every named direction are 20 float64 per sample (a 200 MB log
    # held 1.3 GB of them at once); each row's figures are the same whatever the chunk
    for a in range(0, n, _ROWS_PER_CHUNK):
        part = acc[a:a + _ROWS_PER_CHUNK]
        norm = np.linalg.norm(part, axis=1)
        cos = (part @ _DIRS.T) / np.where(norm > 0, norm, np.inf)[:, None]
        best = np.argmax(cos, axis=1)
        ok = cos[np.arange(part.shape[0]), best] >= limit
        out[a:a + part.shape[0]] = np.where(ok, best, -1)
    return out


def direction_id(position: int) -> int:
    """The direction id (direction_ids) of a position index."""
    return int(_CANON[int(position)])


def direction_name(direction: int) -> str:
    """A direction id in words: the position name ('N', '+x', ...)."""
    return _DIR_NAME[direction] if direction >= 0 else "no position"


def same_direction(a: int, b: int) -> bool:
    """Do two position indices point the same way (sfem-z0 and +x do)?"""
    return direction_id(a) == direction_id(b)


@dataclass
class Placement:
    """One DUT's placement tracker (module doc): feed every sample in order with `update`."""

    settle_s: float = PLACEMENT_SETTLE_S
    max_angle_deg: float = FACING_MAX_ANGLE_DEG
    _run_dir: int = -1  # direction id of the current run of samples (-1: facing none)
    _run_start_s: float = -math.inf  # sample time of the run's first sample
    _last_t_s: float | None = None

    def update(self, time_s: np.ndarray, acc_g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per sample: the direction id it faces (-1: none) and whether the DUT is settled there.
        A long record is walked in chunks (the state carries between them exactly as between two
        calls), so its temporaries stay a chunk's, whatever the record's length."""
        t = np.asarray(time_s, dtype=np.float64).reshape(-1)
        acc = np.asarray(acc_g, dtype=np.float64).reshape(-1, 3)
        n = t.shape[0]
        if n <= _ROWS_PER_CHUNK:
            return self._update(t, acc)
        ids = np.empty(n, dtype=np.int64)
        settled = np.empty(n, dtype=bool)
        for a in range(0, n, _ROWS_PER_CHUNK):
            b = min(a + _ROWS_PER_CHUNK, n)
            ids[a:b], settled[a:b] = self._update(t[a:b], acc[a:b])
        return ids, settled

    def _update(self, t: np.ndarray, acc_g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ids = direction_ids(acc_g, self.max_angle_deg)
        n = t.shape[0]
        if n == 0:
            return ids, np.zeros(0, dtype=bool)
        prev = np.concatenate(([self._run_dir], ids[:-1]))
        new_run = ids != prev
        # start time of each sample's run: the last change at or before it, else the carried run
        k = np.arange(n)
        last_change = np.maximum.accumulate(np.where(new_run, k, -1))
        start = np.where(last_change >= 0, t[np.maximum(last_change, 0)], self._run_start_s)
        settled = (ids >= 0) & (t - start >= self.settle_s)
        self._run_dir = int(ids[-1])
        self._run_start_s = float(start[-1])
        self._last_t_s = float(t[-1])
        return ids, settled

    def placed(self, time_s: np.ndarray, acc_g: np.ndarray, position: int | None) -> np.ndarray:
        """`update`, then per sample: settled facing `position` (all False for None)."""
        ids, settled = self.update(time_s, acc_g)
        if position is None:
            return np.zeros(ids.shape[0], dtype=bool)
        return settled & (ids == direction_id(position))

    def settled_direction(self) -> int | None:
        """The direction id the DUT is settled at after its latest sample (None: moving, facing no
        named position, or not long enough)."""
        if self._run_dir < 0 or self._last_t_s is None or self._last_t_s - self._run_start_s < self.settle_s:
            return None
        return self._run_dir

    def facing_now(self) -> int:
        """The direction id of the latest sample (-1: none), settled or not."""
        return self._run_dir

    def still_for_s(self) -> float:
        """Sample seconds the DUT has faced its current direction (0 when it faces none)."""
        if self._run_dir < 0 or self._last_t_s is None:
            return 0.0
        return self._last_t_s - self._run_start_s


def label_cuts(labels: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) runs of equal label, in order: a stream is cut where its placement changes."""
    lab = np.asarray(labels).reshape(-1)
    cuts = [0, *(np.flatnonzero(np.diff(lab)) + 1).tolist(), lab.shape[0]]
    return list(zip(cuts[:-1], cuts[1:]))


def sequence_labels(time_s: np.ndarray, acc_g: np.ndarray, positions: list[int],
                    settle_s: float = PLACEMENT_SETTLE_S) -> np.ndarray:
    """The station's placement of a whole record whose steps are known but not its labels (a log
    without a position column replayed or judged as a profile's run): the profile's positions in
    order (consecutive repeats merged) are walked by the samples themselves. At each point the
    current position and the next are accepted, a sample settled at the next one moves on to it,
    and once there the positions before are not (a turn back is -1). The daemon's live rule
    (station/daemon/intake.place) gives the same labels for a plate that moves only when asked."""
    seq: list[int] = []
    for p in positions:
        if not seq or not same_direction(seq[-1], int(p)):
            seq.append(int(p))
    ids, settled = Placement(settle_s=settle_s).update(time_s, acc_g)
    labels = np.full(ids.shape[0], -1, dtype=np.int64)
    if not seq:
        return labels
    dirs = [direction_id(p) for p in seq]
    i = 0
    for k in np.flatnonzero(settled):  # a loop over settled samples: the walk is sequential
        if ids[k] == dirs[i]:
            labels[k] = seq[i]
        elif i + 1 < len(seq) and ids[k] == dirs[i + 1]:
            i += 1
            labels[k] = seq[i]
    return labels


def settled_labels(time_s: np.ndarray, acc_g: np.ndarray, position: np.ndarray,
                   settle_s: float = PLACEMENT_SETTLE_S, out: np.ndarray | None = None) -> np.ndarray:
    """A record's own position labels kept only where its samples agree: settled at the labelled
    position (a log whose producer labelled by the button, or switched the label at a turn, keeps
    the turn and the settling out of the fit as the station would). A label of -1 stays -1.
    out: where the labels go (int64, may be the position column itself: each piece is read before
    it is written); a new array by default."""
    pos = np.asarray(position, dtype=np.int64).reshape(-1)
    t = np.asarray(time_s, dtype=np.float64).reshape(-1)
    acc = np.asarray(acc_g, dtype=np.float64).reshape(-1, 3)
    walk = Placement(settle_s=settle_s)
    if out is None:
        out = np.empty(pos.shape[0], dtype=np.int64)
    for a in range(0, pos.shape[0], _ROWS_PER_CHUNK):  # a chunk at a time: the temporaries stay small
        b = a + _ROWS_PER_CHUNK
        p = pos[a:b]
        ids, settled = walk.update(t[a:b], acc[a:b])
        ok = p >= 0
        want = np.full(p.shape[0], -2, dtype=np.int64)
        want[ok] = _CANON[np.clip(p[ok], 0, len(_CANON) - 1)]
        out[a:b] = np.where(ok & settled & (ids == want) & (p < len(_CANON)), p, -1)
    return out
