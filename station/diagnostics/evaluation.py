"""Evaluate one model structure (the baseline plus a list of effects) on every DUT: fits, in-sample
and held-out residuals, pooled RMS.

Why a module of its own: the ranking, the gate and the staircase compare model structures, never
single fits. A ModelEval is that unit of comparison, computed once per effect list (the ranking
caches it), and _spec turns it into the (effects, nonlinear values, Acc0) per DUT that the GLS
comparison (noise_gls.compare) refits under its noise model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from station.diagnostics.fit import DutFit, block_rms, fit_dut, heldout_blocks, predict_blocks, predict_dut, predict_dut_axis
from station.diagnostics.noise_gls import gls_sigma
from station.diagnostics.segmentation import DutData


@dataclass
class ModelEval:
    """A fitted model structure over all DUTs, with its held-out residual on the fit blocks (every
    figure is computed there); the in-sample ones, on the blocks and per sample, are computed when
    asked for (a long log's blocks: 2 MB a model and DUT not kept for each of the ranking's models)."""

    effects: list[str]
    fits: list[DutFit]
    heldout_block: list[np.ndarray]  # per DUT (n_blocks, 3) mg, held-out
    data: list[DutData] = field(repr=False, default_factory=list)
    rms_mg: float = 0.0
    heldout_rms_mg: float = 0.0
    rms_sample_mg: float = 0.0
    heldout_rms_sample_mg: float = 0.0
    n_params: int = 0
    _resid: list[np.ndarray] | None = field(repr=False, default=None)
    _sigma_done: bool = field(repr=False, default=False)

    @property
    def resid_block(self) -> list[np.ndarray]:
        """Per DUT (n_blocks, 3) mg, in-sample: measured block means - the model's, made when asked
        for (the few comparisons that read it) rather than kept for every model the ranking fits."""
        return [d.y_block - predict_blocks(d, f) for d, f in zip(self.data, self.fits)]

    @property
    def resid(self) -> list[np.ndarray]:
        """Per DUT (n, 3) mg: measured - model, sample by sample (plots, saved models)."""
        if self._resid is None:  # measured - model, written over the prediction (one (n, 3) array a DUT)
            self._resid = [np.subtract(d.acc_mg, p, out=p) for d, f in zip(self.data, self.fits)
                           for p in (predict_dut(d, f),)]
        return self._resid

    def resid_axis(self, k: int, axis: int) -> np.ndarray:
        """(n,) DUT k's residual on one axis (measured - model, mg): the cached per-sample residual's
        column when there is one, else made for that axis alone (the noise view reads a column at a
        time: a long log's (n, 3) residual is not kept for it)."""
        if self._resid is not None:
            return self._resid[k][:, axis]
        d = self.data[k]
        return np.subtract(d.acc_mg[:, axis], predict_dut_axis(d, self.fits[k], axis))

    def with_sigma(self) -> "ModelEval":
        """Parameter sigmas from the GLS fit under the residual's noise model (for reported models)."""
        if not self._sigma_done:
            for d, f in zip(self.data, self.fits):
                f.beta_sigma = gls_sigma(d, f)
            self._sigma_done = True
        return self


def _pooled_rms(data: list[DutData], res: list[np.ndarray], basis: str) -> float:
    """RMS over every DUT's samples (each DUT weighted by its sample count)."""
    num = den = 0.0
    for d, r in zip(data, res):
        ok = ~np.isnan(r).any(axis=1)
        if not ok.any():
            continue
        v = block_rms(d, r, basis=basis)
        n = float(d.block_count[ok].sum())
        num += v * v * n
        den += n
    return math.sqrt(num / den) if den else float("nan")


def evaluate(data: list[DutData], effects: list[str], basis: str, n_folds: int,
             nl_start: list[dict] | None = None) -> ModelEval:
    fits, res, held = [], [], []
    for k, d in enumerate(data):
        f = fit_dut(d, effects, nl_start=nl_start[k] if nl_start else None)
        fits.append(f)
        res.append(d.y_block - predict_blocks(d, f))
        held.append(f.heldout_block if f.heldout_block is not None else heldout_blocks(d, effects, f))
    m = ModelEval(effects=list(effects), fits=fits, heldout_block=held, data=data)
    m.rms_mg = _pooled_rms(data, res, basis)
    m.heldout_rms_mg = _pooled_rms(data, held, basis)
    m.rms_sample_mg = _pooled_rms(data, res, "sample")
    m.heldout_rms_sample_mg = _pooled_rms(data, held, "sample")
    m.n_params = sum(int(sum(np.count_nonzero(b) for b in f.beta) + sum(len(v) for v in f.nl.values())) for f in fits)
    return m



def _spec(m: ModelEval) -> list[tuple]:
    return [(list(m.effects), f.nl, f.acc0_g) for f in m.fits]


def _spec_plus(m: ModelEval, cand: ModelEval, name: str) -> list[tuple]:
    """The model m plus candidate `name` at the candidate's own nonlinear values (cheap screen)."""
    out = []
    for f, cf in zip(m.fits, cand.fits):
        nl = {**f.nl, name: cf.nl.get(name, {})}
        out.append((list(m.effects) + [name], nl, f.acc0_g))
    return out


__all__ = ["ModelEval", "evaluate"]
