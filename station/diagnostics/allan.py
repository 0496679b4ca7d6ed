"""Allan deviation of an acceleration residual and the standard noise terms it shows (pure).

Why a module of its own: the noise view (noise_view.py) compares a model's residual with the
sensor's own noise; computing the curves, their honest intervals and the named terms (white,
bias instability, random walk) is the part that does not depend on a diagnosis report.
See noise_view.py for the method in words.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

ONE_SIGMA = math.erf(1.0 / math.sqrt(2.0))
TAU_MAX_FRACTION = 0.25  # longest tau: a quarter of the piece (>= ~4 degrees of freedom)
MIN_PIECE = 16  # samples: shorter NaN-free pieces are skipped
BI_FACTOR = 0.664  # flicker floor of the Allan deviation = 0.664 B (IEEE Std 952)


# ---- Allan deviation --------------------------------------------------------------------------------

@dataclass
class AllanCurve:
    """Overlapping Allan deviation of one series (or of NaN-free pieces pooled), in mg."""

    taus_s: np.ndarray
    adev_mg: np.ndarray
    err_mg: np.ndarray  # allantools' error: adev / sqrt(terms) (optimistic for overlapping estimates)
    lo_mg: np.ndarray  # 1-sigma chi-squared interval from the equivalent degrees of freedom
    hi_mg: np.ndarray
    n_terms: np.ndarray
    edf: np.ndarray
    rate_hz: float
    duration_s: float

    def __len__(self) -> int:
        return int(self.taus_s.shape[0])

    def to_json(self) -> dict:
        return {"taus_s": _list(self.taus_s, 5), "adev_mg": _list(self.adev_mg), "err_mg": _list(self.err_mg),
                "lo_mg": _list(self.lo_mg), "hi_mg": _list(self.hi_mg), "edf": _list(self.edf, 3),
                "rate_hz": _num(self.rate_hz, 6), "duration_s": _num(self.duration_s, 6)}


def _empty(rate_hz: float, duration_s: float = 0.0) -> AllanCurve:
    z = np.zeros(0)
    return AllanCurve(z, z, z, z, z, z, z, float(rate_hz), float(duration_s))


def _pieces(x: np.ndarray) -> list[np.ndarray]:
    """NaN-free contiguous pieces of x, at least MIN_PIECE samples each."""
    x = np.asarray(x, dtype=np.float64).ravel()
    ok = np.isfinite(x)
    if ok.all():
        return [x] if x.size >= MIN_PIECE else []
    edges = np.flatnonzero(np.diff(np.concatenate([[0], ok.astype(np.int8), [0]])))
    return [x[a:b] for a, b in zip(edges[::2], edges[1::2]) if b - a >= MIN_PIECE]


def _edf(n_phase: int, m: int) -> float:
    """Equivalent degrees of freedom of one piece at averaging factor m (NIST SP 1065 Table 5,
    allantools.edf_simple): the fewest of white, flicker and random-walk noise. The noise type is not
    guessed from the curve (its slope at long taus is itself noisy): the interval is the widest of the three."""
    import allantools

    out = [float(allantools.edf_simple(n_phase, m, alpha)) for alpha in (0, -2)]
    if m == 1:  # flicker at m = 1: 2 (N-2)^2 / (2.3 N - 4.9) (SP 1065 Table 5; edf_simple drops the square)
        out.append(2.0 * (n_phase - 2) ** 2 / (2.3 * n_phase - 4.9))
    else:
        out.append(float(allantools.edf_simple(n_phase, m, -1)))
    return min(out)


def allan_pieces(pieces: list[np.ndarray], rate_hz: float) -> AllanCurve:
    """Overlapping Allan deviation pooled over independent pieces (each NaN-free, same rate):
    sigma^2(tau) = sum(n_i sigma_i^2) / sum(n_i), degrees of freedom summed. No joins."""
    import allantools

    rate_hz = float(rate_hz)
    pieces = [np.asarray(p, dtype=np.float64) for p in pieces if len(p) >= MIN_PIECE]
    duration = sum(len(p) for p in pieces) / rate_hz
    if not pieces or rate_hz <= 0:
        return _empty(rate_hz, duration)
    longest = max(len(p) for p in pieces)
    m_all = 2 ** np.arange(int(math.floor(math.log2(max(1, longest * TAU_MAX_FRACTION)))) + 1)
    ssum = np.zeros(m_all.size)
    nsum = np.zeros(m_all.size)
    used: list[tuple[int, np.ndarray]] = []  # (piece length, valid m mask)
    for p in pieces:
        valid = m_all <= len(p) * TAU_MAX_FRACTION
        if not valid.any():
            continue
        taus2, ad, _ade, ns = allantools.oadev(p, rate=rate_hz, data_type="freq", taus=m_all[valid] / rate_hz)
        idx = np.searchsorted(m_all, np.rint(np.asarray(taus2) * rate_hz).astype(np.int64))
        ssum[idx] += np.asarray(ns) * np.asarray(ad) ** 2
        nsum[idx] += np.asarray(ns)
        used.append((len(p), np.isin(np.arange(m_all.size), idx)))
    keep = nsum > 0
    m = m_all[keep]
    taus = m / rate_hz
    adev = np.sqrt(ssum[keep] / nsum[keep])
    edf = np.zeros(m.size)
    for n_p, mask in used:
        for j in np.flatnonzero(mask[keep]):
            edf[j] += max(_edf(n_p + 1, int(m[j])), 0.5)
    edf = np.maximum(edf, 1.0)
    lo, hi = _chi2_interval(adev, edf)
    return AllanCurve(taus_s=taus, adev_mg=adev, err_mg=adev / np.sqrt(nsum[keep]), lo_mg=lo, hi_mg=hi,
                      n_terms=nsum[keep], edf=edf, rate_hz=rate_hz, duration_s=duration)


def _chi2_interval(dev: np.ndarray, edf: np.ndarray, ci: float = ONE_SIGMA) -> tuple[np.ndarray, np.ndarray]:
    """allantools.confidence_interval (NIST SP 1065 eq. 45), vectorised."""
    from scipy.stats import chi2

    lo_p = (1.0 - ci) / 2.0
    var = dev * dev
    return np.sqrt(edf * var / chi2.ppf(1.0 - lo_p, edf)), np.sqrt(edf * var / chi2.ppf(lo_p, edf))


def allan(x_mg: np.ndarray, rate_hz: float) -> AllanCurve:
    """Overlapping Allan deviation of x (mg, sampled at rate_hz) on octave taus 2^k / rate_hz up to a
    quarter of the series; NaN samples split it into pieces that are pooled (allan_pieces)."""
    return allan_pieces(_pieces(x_mg), rate_hz)


# ---- noise terms --------------------------------------------------------------------------------------

def _fmt(v: float | None, unit: str = "") -> str:
    if v is None or not math.isfinite(v):
        return "-"
    s = f"{v:.2g}" if abs(v) < 100 else f"{v:.0f}"
    if "e" in s:
        s = f"{v:.1e}"
    return f"{s} {unit}".rstrip()


def _fmt_tau(t: float) -> str:
    return f"{t:.0f} s" if t >= 100 else f"{t:.2g} s"


def _fit_terms(c: AllanCurve) -> np.ndarray:
    """Non-negative weighted fit of sigma^2(tau) = q/tau^2 + a/tau + b + c tau (coefficients q, a, b, c)."""
    from scipy.optimize import nnls

    t = c.taus_s
    s2 = c.adev_mg ** 2
    rel = np.sqrt(2.0 / c.edf)  # relative standard error of the Allan variance
    A = np.stack([t ** -2.0, 1.0 / t, np.ones_like(t), t], axis=1)
    w = 1.0 / (np.maximum(s2, 1e-300) * rel)
    scale = np.abs(A * w[:, None]).max(axis=0)
    scale[scale == 0] = 1.0
    coef, _ = nnls((A * w[:, None]) / scale, s2 * w)
    return coef / scale


def noise_terms(curve: AllanCurve) -> dict:
    """White noise N (mg/sqrt(Hz), -1/2 slope at 1 s), bias instability B (mg, flat minimum / 0.664) and
    random walk K (mg*sqrt(Hz), +1/2 slope at 3 s) of an Allan curve, each with `present` and a text."""
    t, ad = curve.taus_s, curve.adev_mg
    if len(curve) < 3:
        none = {"present": False, "value": None, "text": "curve too short (fewer than 3 averaging times)"}
        return {"white": {**none, "unit": "mg/sqrt(Hz)"}, "bias_instability": {**none, "unit": "mg"},
                "random_walk": {**none, "unit": "mg*sqrt(Hz)"}, "text": none["text"]}
    q, a, b, c = _fit_terms(curve)
    parts = np.stack([q / t ** 2, a / t, np.full_like(t, b), c * t], axis=1)
    model = parts.sum(axis=1)
    dom = parts > 0.5 * np.maximum(model, 1e-300)[:, None]
    t_lo, t_hi = float(t[0]), float(t[-1])
    out: dict = {"fit": {"quantization_mg": _num(math.sqrt(q / 3.0)), "white_mg_per_sqrt_hz": _num(math.sqrt(a)),
                         "flicker_floor_mg": _num(math.sqrt(b)), "random_walk_mg_sqrt_hz": _num(math.sqrt(3.0 * c)),
                         "model": "sigma^2 = 3 Q^2/tau^2 + N^2/tau + (0.664 B)^2 + K^2 tau/3, weighted NNLS"}}

    # white noise: the -1/2 slope over at least one octave
    wd = np.flatnonzero(dom[:, 1])
    if a > 0 and wd.size >= 2:
        N = math.sqrt(a)
        out["white"] = {"present": True, "value": _num(N), "unit": "mg/sqrt(Hz)", "slope": -0.5, "read_at_tau_s": 1.0,
                        "taus_s": [_num(t[wd[0]], 5), _num(t[wd[-1]], 5)], "text": f"white {_fmt(N, 'mg/sqrt(Hz)')}"}
    else:
        out["white"] = {"present": False, "value": None, "unit": "mg/sqrt(Hz)",
                        "text": f"no white-noise (-1/2) slope from {_fmt_tau(t_lo)} to {_fmt_tau(t_hi)}"}

    # random walk: the +1/2 slope over at least one octave, rising beyond the error bars
    kd = np.flatnonzero(dom[:, 3])
    without = np.sqrt(parts[:, :3].sum(axis=1))
    rises = bool(np.any(curve.lo_mg[kd] > without[kd])) if kd.size else False
    if c > 0 and kd.size >= 2 and rises:
        K = math.sqrt(3.0 * c)
        out["random_walk"] = {"present": True, "value": _num(K), "unit": "mg*sqrt(Hz)", "slope": 0.5,
                              "read_at_tau_s": 3.0, "taus_s": [_num(t[kd[0]], 5), _num(t[kd[-1]], 5)],
                              "text": f"random walk {_fmt(K, 'mg*sqrt(Hz)')} (+1/2 slope from {_fmt_tau(t[kd[0]])})"}
    else:
        out["random_walk"] = {"present": False, "value": None, "unit": "mg*sqrt(Hz)",
                              "text": f"no random walk (+1/2 slope) up to {_fmt_tau(t_hi)}"}

    # bias instability: the minimum, where the curve stops falling (flat, or turning up beyond its error bars)
    k = int(np.argmin(ad))
    fd = np.flatnonzero(dom[:, 2])
    no_floor = np.sqrt(parts[:, [0, 1, 3]].sum(axis=1))
    flat = fd.size >= 2 and bool(np.any(curve.lo_mg[fd] > no_floor[fd]))
    turns_up = k < len(curve) - 1 and bool(np.any(curve.lo_mg[k + 1:] > curve.hi_mg[k]))
    if 0 < k and (flat or turns_up):
        B = float(ad[k]) / BI_FACTOR
        how = "flat minimum" if flat else "minimum between the -1/2 and +1/2 slopes"
        out["bias_instability"] = {"present": True, "value": _num(B), "unit": "mg", "tau_s": _num(t[k], 5),
                                   "flat": flat, "text": f"bias instability {_fmt(B, 'mg')} at {_fmt_tau(t[k])}",
                                   "how": how}
    else:
        why = f"the curve is still falling at {_fmt_tau(t_hi)}" if k >= len(curve) - 2 else "no flat minimum"
        out["bias_instability"] = {"present": False, "value": None, "unit": "mg",
                                   "text": f"no bias instability floor ({why})"}
    out["text"] = ", ".join(out[n]["text"] for n in ("white", "bias_instability", "random_walk"))
    return out


def _num(x, sig: int = 4):
    if x is None:
        return None
    x = float(x)
    if not math.isfinite(x):
        return None
    return float(f"{x:.{sig}g}")


def _list(a, sig: int = 4) -> list:
    return [_num(v, sig) for v in np.asarray(a, dtype=np.float64).ravel()]


__all__ = ["AllanCurve", "allan", "allan_pieces", "noise_terms", "ONE_SIGMA"]
