"""The design matrix of the thermal model (baseline + effects) for one DUT, and whether TDSF has a
lever arm on this data.

Why a module of its own: the fit (fit.py), the GLS comparison (noise_gls.py) and the
identifiability checks (identifiability.py) must all see exactly the same columns, with the same
rule for leaving out a TDSF the orientations cannot identify; building them in one place keeps a
candidate from being judged on a different regressor than the one it is fitted with.
"""

from __future__ import annotations

import numpy as np

from station.diagnostics.effects import Context, Effect
from station.diagnostics.segmentation import DutData
from contracts.types import T_REF_C


TDSF_MIN_SPREAD_G = 0.25  # TDSF needs orientations whose Acc0 on the axis differ by at least this


def tdsf_identifiable(acc0_g: np.ndarray) -> np.ndarray:
    """(3,) bool: per axis, do the orientations seen give TDSF a lever arm (Acc0 spread)?

    TDSF multiplies Acc0 (martinez2022 eq. 1): with one orientation, or orientations with the same
    Acc0 on an axis, dT TDSF Acc0 is a multiple of dT and only the total drift TDB + TDSF Acc0 is
    measurable. The column is then left out (TDSF = 0, TDB = the total drift), never fitted to noise.
    """
    a = np.asarray(acc0_g, float)
    ok = ~np.isnan(a).any(axis=1)
    if ok.sum() < 2:
        return np.zeros(3, bool)
    return (a[ok].max(axis=0) - a[ok].min(axis=0)) >= TDSF_MIN_SPREAD_G


class _Design:
    """Builds the per-sample design matrix for a DUT, an effect list and nonlinear values."""

    def __init__(self, d: DutData, effects: list[Effect]):
        self.d = d
        self.effects = effects
        self.lag = [e for e in effects if type(e).temperature is not Effect.temperature]

    def temp_seen(self, nl: dict[str, dict[str, float]], block: bool = False) -> np.ndarray:
        d = self.d
        t, time_s = (d.block_temp_c, d.block_time_s) if block else (d.temp_c, d.time_s)
        for e in self.lag:
            t2 = e.temperature(t, time_s, nl.get(e.name, {}))
            if t2 is not None:
                t = t2
        return t

    def context(self, nl, acc0_sample_g: np.ndarray) -> Context:
        """Per-sample context: predictions and compensation, sample by sample."""
        d = self.d
        return Context(time_s=d.time_s, temp_c=d.temp_c, temp_smooth_c=d.temp_smooth_c,
                       dt_c=self.temp_seen(nl) - T_REF_C, acc0_g=acc0_sample_g,
                       t_power_on_s=d.t_power_on_s, cache=d.cache)

    def block_context(self, nl, acc0_block_g: np.ndarray) -> Context:
        """Context on the 10 s fit blocks (their mean time and temperatures): every fit, held-out
        prediction and comparison runs on these, ~30x fewer rows than samples. A term is evaluated
        at the block's mean temperature, not averaged over its samples; the two differ by the
        temperature's scatter inside 10 s (its quantization steps), far below the noise."""
        d = self.d
        return Context(time_s=d.block_time_s, temp_c=d.block_temp_c, temp_smooth_c=d.block_temp_smooth_c,
                       dt_c=self.temp_seen(nl, block=True) - T_REF_C, acc0_g=acc0_block_g,
                       t_power_on_s=d.t_power_on_s, cache=d.block_cache)

    def names(self) -> list[list[str]]:
        d = self.d
        out = []
        for _ in range(3):
            nm = [f"acc0_g[{lab}]" for lab in d.pos_labels] + ["tdb_mg_per_c", "tdsf_ppm_per_c"]
            for e in self.effects:
                nm += [f"{e.name}.{ln}" for ln in e.linear]
            out.append(nm)
        return out

    def block_matrices(self, nl, acc0_g: np.ndarray) -> tuple[list[np.ndarray], list[list[str]]]:
        """Per axis: the design on the fit blocks (n_blocks, k), the parameters named by names().

        Every fit block lies inside one constant-orientation run, so Acc0 is constant over a
        block; the other columns are the terms at the block's mean time and temperatures.
        """
        d = self.d
        P = len(d.pos_labels)
        a0 = np.nan_to_num(acc0_g)
        a0_blocks = a0[d.block_pos]
        if self.effects:
            ctx = self.block_context(nl, a0_blocks)
            dtb = ctx.dt_c
            sample_ctx = None
            extra = []
            for e in self.effects:
                if e.block_level:
                    extra.append(e.columns(ctx, nl.get(e.name, {})))
                    continue
                # a term that did not declare itself smooth within 10 s (a user's effect) is
                # evaluated sample by sample and averaged over each block: exact for any term
                sample_ctx = sample_ctx or self.context(nl, a0[d.pos])
                c = e.columns(sample_ctx, nl.get(e.name, {}))
                extra.append(d.block_mean(c.reshape(d.n, -1)).reshape(-1, 3, c.shape[2]))
        else:
            dtb = d.block_cache.get("_dt_c")
            if dtb is None:
                dtb = d.block_cache["_dt_c"] = self.temp_seen(nl, block=True) - T_REF_C
            extra = []
        ind = d.block_cache.get("_block_indicator")
        if ind is None or ind.shape[1] != P:
            ind = np.zeros((d.block_starts.shape[0], P))
            ind[np.arange(ind.shape[0]), d.block_pos] = 1000.0
            d.block_cache["_block_indicator"] = ind
        a0b = a0_blocks * tdsf_identifiable(acc0_g)[None, :]
        eff_blocks = [c for c in extra if c.shape[2]]
        mats = []
        for i in range(3):
            cols = [ind, dtb[:, None], (dtb * a0b[:, i] * 1e-3)[:, None]] + [eb[:, i, :] for eb in eff_blocks]
            mats.append(np.hstack(cols))
        return mats, self.names()


__all__ = ["tdsf_identifiable", "TDSF_MIN_SPREAD_G"]
