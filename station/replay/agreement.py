"""Did the replayed plate do what the recorded one did? (pure: columns in, a report out)

The station stores beside every sample the lamp state and fixture position it had commanded when
it took that sample in. A replay stores the same columns for the same samples (its boards send
the recorded samples, in order), so the two are compared sample by sample: where the replay's
daemon had the lamp off while the recording had it on (or the fixture elsewhere), the data it
was given were measured under another plate state than it believed. Short disagreements are
command latency (in compressed time a wall-clock delay is many sample seconds, and it differs
between the recording and the replay); one longer than `window_s` of sample time is reported.
"""

from __future__ import annotations

import numpy as np


def episodes(time_s: np.ndarray, replay: np.ndarray, recorded: np.ndarray, valid: np.ndarray,
             window_s: float) -> tuple[float, float, list[dict]]:
    """(seconds compared, seconds disagreeing, disagreements longer than window_s)."""
    t = np.asarray(time_s, dtype=np.float64)
    if len(t) < 2:
        return 0.0, 0.0, []
    dt = np.diff(t, append=t[-1] + np.median(np.diff(t)))
    ok = np.asarray(valid, dtype=bool)
    rep = np.asarray(replay, dtype=np.int64)
    rec = np.asarray(recorded, dtype=np.int64)
    bad = ok & (rep != rec)
    checked = float(dt[ok].sum())
    out = []
    # runs of consecutive disagreeing samples (samples not compared neither break nor extend a run)
    idx = np.flatnonzero(ok)
    if len(idx):
        b = bad[idx]
        key = np.where(b, rep[idx] * 1_000_003 + rec[idx], -1)
        edges = np.flatnonzero(np.diff(key) != 0) + 1
        for a, z in zip(np.r_[0, edges], np.r_[edges, len(idx)]):
            if key[a] < 0:
                continue
            t0, t1 = float(t[idx[a]]), float(t[idx[z - 1]] + dt[idx[z - 1]])
            if t1 - t0 > window_s:
                out.append({"from_s": round(t0, 3), "to_s": round(t1, 3), "duration_s": round(t1 - t0, 3),
                            "replay": int(rep[idx[a]]), "recorded": int(rec[idx[a]])})
    return checked, float(dt[bad].sum()), out


def plate_agreement(recorded_time_s: np.ndarray, recorded_lamp: np.ndarray | None,
                    recorded_position: np.ndarray | None, replay_time_s: np.ndarray, replay_lamp: np.ndarray,
                    replay_position: np.ndarray, window_s: float) -> dict:
    """Lamp and fixture of a replay against the recording, over the samples both have (matched
    by their sample time, which the replay board sends as recorded)."""
    out: dict = {"window_s": window_s}
    if recorded_lamp is None:
        out["note"] = "the recording has no lamp/position columns: the plate cannot be compared"
        out["agrees"] = None
        return out
    rec_t = np.asarray(recorded_time_s, dtype=np.float64)
    rep_t = np.asarray(replay_time_s, dtype=np.float64)
    k = np.clip(np.searchsorted(rec_t, rep_t), 0, max(0, len(rec_t) - 1))
    hit = np.abs(rec_t[k] - rep_t) <= 0.5e-6 if len(rec_t) else np.zeros(len(rep_t), bool)
    out["samples"] = int(hit.sum())
    t, k = rep_t[hit], k[hit]
    checked, bad, eps = episodes(t, np.asarray(replay_lamp)[hit], np.asarray(recorded_lamp)[k], np.ones(len(t), bool),
                                 window_s)
    out["lamp"] = {"checked_s": round(checked, 3), "disagree_s": round(bad, 3), "agrees": not eps, "episodes": eps}
    if recorded_position is not None:
        rp, pp = np.asarray(recorded_position)[k], np.asarray(replay_position)[hit]
        checked, bad, eps = episodes(t, pp, rp, (rp >= 0) & (pp >= 0), window_s)  # -1: moving
        out["fixture"] = {"checked_s": round(checked, 3), "disagree_s": round(bad, 3), "agrees": not eps,
                          "episodes": eps}
    out["agrees"] = all(v["agrees"] for k2, v in out.items() if k2 in ("lamp", "fixture"))
    return out


# What a disagreement means, by device (printed with every episode: a bare "DISAGREES" says nothing).
WHY = {
    "lamp": ("the replayed samples were measured under the recorded lamp whatever this daemon commanded; "
             "no result reads the lamp column (TDB/TDSF/SFEM come from the samples), so the results above "
             "are not changed by it, but live hardware under this daemon would have been heated otherwise"),
    "fixture": ("this daemon believed the plate at another position than the recorded one: segments of that "
                "time carry its position, so position-dependent results (TDSF sign, SFEM) can change; "
                "the per-DUT changes above say whether they did"),
}
STATE_WORDS = {"lamp": {0: "off", 1: "on"}}


def describe_episode(device: str, ep: dict, step: str | None = None) -> str:
    """One line for one disagreement: what, when (sample time), during which replayed step, why
    it matters or not."""
    words = STATE_WORDS.get(device, {})
    rep = words.get(ep["replay"], f"position {ep['replay']}")
    rec = words.get(ep["recorded"], f"position {ep['recorded']}")
    where = f" during step {step}" if step else ""
    return (f"{device}: replay {rep}, recorded {rec}, from {ep['from_s']:.0f} s to {ep['to_s']:.0f} s of sample time "
            f"({ep['duration_s']:.0f} s){where}: {WHY.get(device, '')}")


def step_at(step_spans: list[tuple[float, float, str]], t_s: float) -> str | None:
    """The name of the replayed step whose sample-time span holds t_s (None: between steps)."""
    for a, b, name in step_spans:
        if a < t_s <= b:
            return name
    return None
