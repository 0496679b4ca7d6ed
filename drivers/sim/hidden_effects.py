"""The hidden effects of a simulated world's DUTs: what each adds to its acceleration.

physics.py draws an effect's parameters (DutTruth.effects, `_draw_effect`); this module is how the
world applies them, vectorized over the DUTs of one SimWorld (drivers/sim/world.py): every effect
as arrays over DUTs, zeros where a DUT does not have it, and the one effect with state of its own
(hysteresis). `thermal_lag` is applied by the world's thermal chain (it delays the MEMS, not the
acceleration): its time constants are here (`fx["lag_tau"]`) for the world to read.
"""

from __future__ import annotations

import numpy as np

from drivers.sim.physics import DutTruth


class HiddenEffects:
    """Every DUT's hidden effects as arrays over DUTs; `has` names those any DUT has."""

    def __init__(self, duts: list[DutTruth]) -> None:
        n = len(duts)

        def z3() -> np.ndarray:
            return np.zeros((n, 3))

        fx = {
            "c2": z3(), "c3": z3(), "k2": z3(), "lag_tau": np.zeros(n), "h": z3(), "h_width": np.ones(n),
            "w": z3(), "w_tau": np.ones(n), "x": np.zeros((n, 3, 3)), "nl": z3(),
        }
        self.has: set[str] = set()
        for i, t in enumerate(duts):
            for name, p in t.effects.items():
                self.has.add(name)
                if name == "bias_t2":
                    fx["c2"][i] = np.asarray(p["c2_mg_per_c2"]) * 1e-3
                elif name == "bias_t3":
                    fx["c3"][i] = np.asarray(p["c3_mg_per_c3"]) * 1e-3
                elif name == "scale_t2":
                    fx["k2"][i] = np.asarray(p["k2_ppm_per_c2"]) * 1e-6
                elif name == "thermal_lag":
                    fx["lag_tau"][i] = float(p["tau_s"])
                elif name == "hysteresis":
                    fx["h"][i] = np.asarray(p["h_mg"]) * 1e-3
                    fx["h_width"][i] = float(p["width_c"])
                elif name == "self_heating":
                    fx["w"][i] = np.asarray(p["w_mg"]) * 1e-3
                    fx["w_tau"][i] = float(p["tau_s"])
                elif name == "cross_axis":
                    x = np.asarray(p["x_ppm_per_c"], dtype=np.float64).reshape(3, 3) * 1e-6
                    fx["x"][i] = x - np.diag(np.diag(x))
                elif name == "scale_nonlinearity":
                    fx["nl"][i] = np.asarray(p["n_ppm_per_c_per_g"]) * 1e-6
        self.fx: dict[str, np.ndarray] = fx
        self._n = n
        self._hyst_z = np.zeros(n)  # hysteresis state, carried from chunk to chunk

    def acceleration(self, acc0: np.ndarray, dT: np.ndarray, die: np.ndarray, die_before: np.ndarray,
                     since_on: np.ndarray, n: int) -> np.ndarray:
        """(n_duts, n, 3) g the effects add to a chunk of n samples. acc0 (n_duts, 3): the
        acceleration at T_REF_C; dT (n_duts, n, 1): MEMS temperature - T_REF_C; die (n_duts, n)
        and die_before (n_duts,): the die's temperature over the chunk and just before it;
        since_on (n_duts, n): seconds since power-up."""
        fx = self.fx
        has = self.has
        out = np.zeros((self._n, n, 3))
        if "bias_t2" in has:
            out += fx["c2"][:, None, :] * dT**2
        if "bias_t3" in has:
            out += fx["c3"][:, None, :] * dT**3
        if "scale_t2" in has:
            out += (fx["k2"] * acc0)[:, None, :] * dT**2
        if "cross_axis" in has:
            out += dT * np.einsum("dij,dj->di", fx["x"], acc0)[:, None, :]
        if "scale_nonlinearity" in has:
            out += dT * (fx["nl"] * acc0**2)[:, None, :]
        if "self_heating" in has:
            out += fx["w"][:, None, :] * np.exp(-since_on / fx["w_tau"][:, None])[:, :, None]
        if "hysteresis" in has:
            z = self._hysteresis_state(die, die_before, n)
            out += fx["h"][:, None, :] * z[:, :, None]
        return out

    def _hysteresis_state(self, die: np.ndarray, die_before: np.ndarray, n: int) -> np.ndarray:
        """Play-type state z in [-1, 1]: z_k = s + (z_{k-1} - s) exp(-|dT_k| / width), s = sign(dT_k)."""
        d = np.diff(die, axis=1, prepend=die_before[:, None])
        s = np.sign(d)
        decay = np.exp(-np.abs(d) / self.fx["h_width"][:, None])
        z = np.empty_like(die)
        zk = self._hyst_z.copy()
        for k in range(n):
            zk = s[:, k] + (zk - s[:, k]) * decay[:, k]
            z[:, k] = zk
        self._hyst_z = zk
        return z
