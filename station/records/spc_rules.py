"""Run rules of an individuals chart (Western Electric / Nelson) and the moving-range flag. Pure.

Why more than "beyond 3 sigma": a drifting fixture or a new sensor lot shows as a run or a trend
long before one part leaves the control limits. Numbering and definitions as Nelson (1984, J.
Quality Technology 16(4)) and Minitab; sigma is the chart's sigma_within (MR-bar / d2), zones are
measured from the centre line (the mean of the group):

    1  one point beyond 3 sigma (either side)
    2  9 points in a row on the same side of the centre line
    3  6 points in a row steadily increasing or steadily decreasing
    4  14 points in a row alternating up and down
    5  2 of 3 points in a row beyond 2 sigma on the same side
    6  4 of 5 points in a row beyond 1 sigma on the same side
    7  15 points in a row within 1 sigma (either side): stratification, sigma overestimated
    8  8 points in a row beyond 1 sigma, on both sides, none within: a mixture of two streams
    MR a moving range above its upper limit D4 * MR-bar (a jump between consecutive parts)

Which point carries a flag: the one that completes the pattern, and every later point that keeps
it going (as Minitab marks them), so a flag never points at a part made before the evidence. For 5
and 6 the flagged point is itself beyond the zone on that side (a window whose last point is
inside was already flagged at its earlier point); at the start of the series the window is what
there is (2 of the first 2 counts for rule 5).

Ties: a point exactly on the centre line is on neither side (it breaks rule 2); equal neighbours
go neither up nor down (they break rules 3 and 4); "beyond k sigma" is strictly more than k sigma
from the centre, "within 1 sigma" is at most 1 sigma, so rules 7 and 8 never share a point. The
zone rules (1, 5-8) need sigma > 0; rules 2-4 need only the order and the centre.
"""

from __future__ import annotations

from typing import Callable, Sequence

RULE_NAMES: dict[str, str] = {
    "1": "beyond 3 sigma",
    "2": "9 in a row on one side of the centre line",
    "3": "6 in a row steadily increasing or decreasing",
    "4": "14 in a row alternating up and down",
    "5": "2 of 3 beyond 2 sigma on one side",
    "6": "4 of 5 beyond 1 sigma on one side",
    "7": "15 in a row within 1 sigma",
    "8": "8 in a row beyond 1 sigma on both sides",
    "MR": "moving range above D4 x MR-bar",
}


def _sign(v: float) -> int:
    return (v > 0) - (v < 0)


def _run_ends(ok: Sequence[bool], length: int) -> set[int]:
    """Indices i where ok[i-length+1 .. i] are all true (the point completing a run of `length`,
    and every later point of the same run)."""
    out, run = set(), 0
    for i, good in enumerate(ok):
        run = run + 1 if good else 0
        if run >= length:
            out.add(i)
    return out


def rule1(x: Sequence[float], mean: float, sigma: float) -> set[int]:
    if sigma <= 0:
        return set()
    return {i for i, v in enumerate(x) if abs(v - mean) > 3 * sigma}


def rule2(x: Sequence[float], mean: float, sigma: float = 0.0, length: int = 9) -> set[int]:
    out: set[int] = set()
    for side in (1, -1):
        out |= _run_ends([_sign(v - mean) == side for v in x], length)
    return out


def _steps(x: Sequence[float]) -> list[int]:
    """+1 / -1 / 0 for each step x[i-1] -> x[i], at index i (index 0 has no step: 0)."""
    return [0] + [_sign(x[i] - x[i - 1]) for i in range(1, len(x))]


def rule3(x: Sequence[float], mean: float = 0.0, sigma: float = 0.0, length: int = 6) -> set[int]:
    """6 points = 5 steps, all up or all down."""
    d = _steps(x)
    out: set[int] = set()
    for side in (1, -1):
        out |= _run_ends([s == side for s in d], length - 1)
    return out


def rule4(x: Sequence[float], mean: float = 0.0, sigma: float = 0.0, length: int = 14) -> set[int]:
    """14 points = 13 steps, each the opposite direction of the one before."""
    d = _steps(x)
    alternating = [False] + [i >= 2 and d[i] != 0 and d[i - 1] != 0 and d[i] == -d[i - 1] for i in range(1, len(x))]
    # a run of k alternations covers k + 1 steps = k + 2 points
    return _run_ends(alternating, length - 2)


def _k_of_m(x: Sequence[float], mean: float, sigma: float, zone: float, k: int, m: int) -> set[int]:
    if sigma <= 0:
        return set()
    out: set[int] = set()
    for side in (1, -1):
        beyond = [side * (v - mean) > zone * sigma for v in x]
        for i in range(len(x)):
            if beyond[i] and sum(beyond[max(0, i - m + 1): i + 1]) >= k:
                out.add(i)
    return out


def rule5(x: Sequence[float], mean: float, sigma: float) -> set[int]:
    return _k_of_m(x, mean, sigma, 2.0, 2, 3)


def rule6(x: Sequence[float], mean: float, sigma: float) -> set[int]:
    return _k_of_m(x, mean, sigma, 1.0, 4, 5)


def rule7(x: Sequence[float], mean: float, sigma: float, length: int = 15) -> set[int]:
    if sigma <= 0:
        return set()
    return _run_ends([abs(v - mean) <= sigma for v in x], length)


def rule8(x: Sequence[float], mean: float, sigma: float, length: int = 8) -> set[int]:
    if sigma <= 0:
        return set()
    out: set[int] = set()
    for i in _run_ends([abs(v - mean) > sigma for v in x], length):
        window = x[i - length + 1: i + 1]
        if any(v > mean for v in window) and any(v < mean for v in window):
            out.add(i)
    return out


RULES: dict[str, Callable[..., set[int]]] = {"1": rule1, "2": rule2, "3": rule3, "4": rule4, "5": rule5,
                                             "6": rule6, "7": rule7, "8": rule8}


def moving_range_flags(x: Sequence[float], mr_ucl: float | None) -> set[int]:
    """Point i when |x[i] - x[i-1]| > mr_ucl (the moving range ending at it)."""
    if mr_ucl is None or mr_ucl <= 0:
        return set()
    return {i for i in range(1, len(x)) if abs(x[i] - x[i - 1]) > mr_ucl}


def flags(x: Sequence[float], mean: float | None, sigma: float | None, mr_ucl: float | None) -> list[list[str]]:
    """Per point, the codes of the rules it is flagged by ("1".."8", then "MR"), in that order."""
    out: list[list[str]] = [[] for _ in x]
    if mean is None or len(x) < 2:
        return out
    s = sigma or 0.0
    for code, rule in RULES.items():
        for i in rule(x, mean, s):
            out[i].append(code)
    for i in moving_range_flags(x, mr_ucl):
        out[i].append("MR")
    return out


__all__ = ["RULE_NAMES", "RULES", "rule1", "rule2", "rule3", "rule4", "rule5", "rule6", "rule7", "rule8",
           "moving_range_flags", "flags"]
