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
    """Builds the per-sample design matrix for a DUT, an effect list and nonlinear values.

    One instance serves every evaluation of one fit (a variable-projection search calls
    block_matrices hundreds of times with the same Acc0 and new nonlinear values): what depends
    only on the data, the effect list or Acc0 is computed once and kept (names, the Acc0 columns
    of the last Acc0 seen)."""

    def __init__(self, d: DutData, effects: list[Effect]):
        self.d = d
        self.effects = effects
        self.lag = [e for e in effects if type(e).temperature is not Effect.temperature]
        self._names: list[list[str]] | None = None
        self._acc0_key: bytes | None = None
        self._acc0_cols: tuple[np.ndarray, np.ndarray, np.ndarray] = (np.zeros((0, 3)),) * 3
        self._temp_smooth: np.ndarray | None = None  # the per-sample one, made once per design

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
        if self._temp_smooth is None:
            self._temp_smooth = d.temp_smooth_c
        return Context(time_s=d.time_s, temp_c=d.temp_c, temp_smooth_c=self._temp_smooth,
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
        if self._names is None:
            d = self.d
            out = []
            for _ in range(3):
                nm = [f"acc0_g[{lab}]" for lab in d.pos_labels] + ["tdb_mg_per_c", "tdsf_ppm_per_c"]
                for e in self.effects:
                    nm += [f"{e.name}.{ln}" for ln in e.linear]
                out.append(nm)
            self._names = out
        return [list(nm) for nm in self._names]

    def _acc0_columns(self, acc0_g: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(Acc0 per sample's orientation with NaN as 0, the same per block, the per-block Acc0 that
        multiplies TDSF: 0 on an axis where TDSF is not identifiable) for this Acc0; the last one is kept."""
        key = acc0_g.tobytes() + str(acc0_g.shape).encode()
        if key != self._acc0_key:
            a0 = np.nan_to_num(acc0_g)
            a0_blocks = a0[self.d.block_pos]
            self._acc0_cols = (a0, a0_blocks, a0_blocks * tdsf_identifiable(acc0_g)[None, :])
            self._acc0_key = key
        return self._acc0_cols

    def _indicator(self) -> np.ndarray:
        d = self.d
        P = len(d.pos_labels)
        ind = d.block_cache.get("_block_indicator")
        if ind is None or ind.shape[1] != P:
            ind = np.zeros((d.block_starts.shape[0], P))
            ind[np.arange(ind.shape[0]), d.block_pos] = 1000.0
            d.block_cache["_block_indicator"] = ind
        return ind

    def block_parts(self, nl, acc0_g: np.ndarray) -> "_BlockParts":
        """The columns of the design on the fit blocks, not yet laid out per axis (block_matrices)."""
        d = self.d
        a0, a0_blocks, a0b = self._acc0_columns(acc0_g)
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
        return _BlockParts(self._indicator(), dtb, a0b, [c for c in extra if c.shape[2]])

    def block_matrices(self, nl, acc0_g: np.ndarray) -> tuple[list[np.ndarray], list[list[str]]]:
        """Per axis: the design on the fit blocks (n_blocks, k), the parameters named by names().

        Every fit block lies inside one constant-orientation run, so Acc0 is constant over a
        block; the other columns are the terms at the block's mean time and temperatures.
        """
        parts = self.block_parts(nl, acc0_g)
        return [parts.matrix(i) for i in range(3)], self.names()


class _BlockParts:
    """The design's columns on (some of) the fit blocks: the orientation indicator (x 1000, for
    Acc0 in g), dT, the Acc0 that multiplies TDSF per axis, and the effects' columns (n, 3, m)."""

    def __init__(self, ind: np.ndarray, dtb: np.ndarray, a0b: np.ndarray, effects: list[np.ndarray]) -> None:
        self.ind, self.dtb, self.a0b, self.effects = ind, dtb, a0b, effects
        self.n_effect_cols = sum(c.shape[2] for c in effects)

    def rows(self, rows: np.ndarray) -> "_BlockParts":
        """The same columns on the blocks `rows` (indices) only."""
        return _BlockParts(self.ind[rows], self.dtb[rows], self.a0b[rows], [c[rows] for c in self.effects])

    def matrix(self, i: int) -> np.ndarray:
        """Axis i's design (n, k): [indicator, dT, dT Acc0_i 1e-3, effect columns of axis i]."""
        ind, dtb = self.ind, self.dtb
        P = ind.shape[1]
        m = np.empty((ind.shape[0], P + 2 + self.n_effect_cols))
        m[:, :P] = ind
        m[:, P] = dtb
        m[:, P + 1] = dtb * self.a0b[:, i] * 1e-3
        j = P + 2
        for eb in self.effects:
            m[:, j:j + eb.shape[2]] = eb[:, i, :]
            j += eb.shape[2]
        return m

    def effect_absmax(self) -> np.ndarray:
        """(3, m): per axis, the largest |value| of each effect column (column by column: numpy
        reduces (n, 3, m) over its first axis 5-10x slower than each of its 3 m columns)."""
        if not self.effects:
            return np.zeros((3, 0))
        out = []
        for c in self.effects:
            flat = c.reshape(c.shape[0], -1)
            out.append(np.array([np.abs(flat[:, j]).max() for j in range(flat.shape[1])]).reshape(3, c.shape[2]))
        return np.concatenate(out, axis=1)


__all__ = ["tdsf_identifiable", "TDSF_MIN_SPREAD_G"]
