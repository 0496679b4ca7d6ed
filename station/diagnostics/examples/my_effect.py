"""Example user effect for `station diagnose --effects-file` (see docs/diagnostics.md).

`bias_rate`: a bias proportional to the rate of temperature change, + r_i dT/dt. Physics: during a
ramp the package is not isothermal; the thermal gradient stresses the MEMS and shifts its bias in
proportion to the rate. (To first order in its time constant, a thermal lag looks like such a term
too, which is why the library's `thermal_lag` and this one compete on lag data.)

Run:
    station diagnose LOG.csv --effects-file station/diagnostics/examples/my_effect.py --add bias_rate
"""

from __future__ import annotations

import numpy as np

from station.diagnostics.effects import Effect, register, smooth_temperature


class BiasRate(Effect):
    name = "bias_rate"
    note = "bias proportional to the temperature rate: + r dT/dt (thermal-gradient stress during ramps)"
    needs = "temperature ramps, heating and cooling (dT/dt of both signs)"
    identify_hint = "ramp up and down at a known rate"
    linear = ("r_mg_per_c_per_min",)  # one amplitude per axis, unit in the name
    nonlinear = ()  # no shared nonlinear parameters

    def columns(self, ctx, nl):
        """(n, 3, 1): the regressor of each axis, in mg per unit of r."""
        key = "bias_rate.rate_c_per_min"
        rate = ctx.cache.get(key)  # ctx.cache lives as long as the prepared log: reuse across fits
        if rate is None:
            # 5-minute smoothing of the measured temperature: its 1 C quantization steps would
            # otherwise make the derivative a train of spikes
            smooth = smooth_temperature(ctx.temp_c, ctx.time_s, window_s=300.0)
            rate = np.gradient(smooth, ctx.time_s) * 60.0
            ctx.cache[key] = rate
        return np.repeat(rate[:, None, None], 3, axis=1)


register(BiasRate())
