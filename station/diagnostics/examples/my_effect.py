"""Example user effect for `station diagnose --effects-file` (see docs/diagnostics.md, "Your own effect").

`coating_knee`: the bias drift changes slope at a temperature, + k_i max(T - T_knee, 0). Physics: a
conformal coating or potting over the accelerometer (acrylic, polyurethane: glass transition
~30-60 C) is stiff below its glass transition and pulls on the package with a stress linear in
temperature (eq. 1's TDB absorbs that); above it the coating softens and the stress, so the bias
drift, changes slope at T_knee. One amplitude per axis (k, mg/C) and one shared nonlinear parameter
(the knee, C), fitted by variable projection like the library's time constants.

Run:
    station diagnose LOG.csv --effects-file station/diagnostics/examples/my_effect.py --add coating_knee
"""

from __future__ import annotations

import numpy as np

from station.diagnostics.effects import T_REF_C, Effect, NonlinearParam, register


class CoatingKnee(Effect):
    name = "coating_knee"
    note = "bias slope changes at a knee: + k max(T - T_knee, 0) (a coating or potting past its glass transition)"
    needs = "temperatures on both sides of the knee (a ramp across it, in any orientation)"
    identify_hint = "ramp from well below to well above the coating's glass transition"
    linear = ("k_mg_per_c",)  # one amplitude per axis, unit in the name
    # shared by the three axes; searched on a coarse grid of 15 knees (linear, not log, spacing),
    # then refined by Brent's method
    nonlinear = (NonlinearParam("knee_c", "C", 40.0, 0.0, 70.0, log=False, grid=15),)
    # block_level = True would evaluate the term at the 10 s block means (faster, fine for a smooth
    # term like this one); the default evaluates it sample by sample and averages each block (exact)

    def columns(self, ctx, nl):
        """(n, 3, 1): the regressor of each axis, in mg per unit of k (mg/C)."""
        t_mems = ctx.dt_c + T_REF_C  # the temperature the MEMS sees (lagged when thermal_lag is in the model)
        knee = np.maximum(t_mems - nl["knee_c"], 0.0)
        return np.repeat(knee[:, None, None], 3, axis=1)


register(CoatingKnee())
