"""What a fold of the held-out validation can learn: the effect columns its training blocks hold
enough of to fit.

Why a module of its own: the fit (fit._inner) and the leftover's noise draws (leftover._heldout)
must leave out exactly the same terms in a fold, or the leftover would compare the held-out error
with draws predicted by a different model.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg.lapack import dpotrf, dpotrs

SUPPORT_MIN = 0.3  # a fold fits an effect column only where its training blocks hold this share of it


def unsupported(X_full: np.ndarray, rows: np.ndarray, P: int, X_train: np.ndarray | None = None) -> np.ndarray:
    """(k_effect,) bool: effect columns a fold's training blocks cannot learn.

    What the baseline (Acc0 per orientation, TDB, TDSF) cannot explain of a column is its signal;
    a fold whose training blocks hold less than SUPPORT_MIN of that signal (its norm) would fit it
    to the noise and extrapolate it into the held-out leg: a bias step whose one side is held out
    (inside the training data the step is an orientation's offset: 17 mg held-out errors), a
    warm-up transient whose head is held out (fitted on its tail and extrapolated 14x). Such a
    column is left out of that fold's fit, so the held-out leg is predicted without the term, as the
    baseline predicts it; the folds that can learn the term show whether it generalises.
    X_train: X_full[rows] when the caller has it already."""
    E = X_full[:, P + 2:]
    if not E.shape[1]:
        return np.zeros(0, bool)

    def signal(X: np.ndarray) -> np.ndarray:
        B, Ek = X[:, :P + 2], X[:, P + 2:]
        norm = np.sqrt(np.einsum("ij,ij->j", B, B))
        live = norm > 0  # the baseline's columns with a value on these blocks
        if not live.any():
            return np.sqrt(np.einsum("ij,ij->j", Ek, Ek))
        return _span_residual_norms(B[:, live], Ek, norm[live])

    full = signal(X_full)
    train = signal(X_full[rows] if X_train is None else X_train)
    return (full > 0) & (train < SUPPORT_MIN * full)


def _span_residual_norms(B: np.ndarray, E: np.ndarray, norm: np.ndarray) -> np.ndarray:
    """(m,): the norm of each column of E left after its least-squares projection on the columns
    of B (none zero; `norm` their norms). The normal equations of the unit-scaled columns by
    Cholesky when they are well conditioned (a fold's baseline: a few columns over thousands of
    blocks, 3-5x faster than lstsq's SVD, which runs for every fold, pass and axis), else lstsq;
    the two agree to ~1e-14 of the column's norm there (cond(G) <= 1e8; measured on the
    diagnoses of tests/diag_helpers' logs: no decision of unsupported() changes)."""
    Bs = B / norm
    c, info = dpotrf(Bs.T @ Bs, lower=0, clean=0, overwrite_a=0)
    if info == 0:
        dg = np.abs(np.diag(c))
        if dg.min() >= 1e-4 * dg.max():
            coef, info = dpotrs(c, Bs.T @ E, lower=0, overwrite_b=0)
            if info == 0:
                R = E - Bs @ coef
                return np.sqrt(np.einsum("ij,ij->j", R, R))
    coef, *_ = np.linalg.lstsq(B, E, rcond=None)
    R = E - B @ coef
    return np.sqrt(np.einsum("ij,ij->j", R, R))


__all__ = ["SUPPORT_MIN", "unsupported"]
