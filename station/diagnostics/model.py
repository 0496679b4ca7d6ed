"""The saved diagnostic model: baseline + effects with their fitted values per DUT, as versioned
JSON, and the compensation that inverts it.

Why a module of its own: this is what leaves a diagnosis (`station diagnose --save-model`, the web
page's model.json) and what is loaded later to compensate readings. It must stay readable by later
code (format and version are checked on load), and predicting or compensating needs only the
effect library, not the fit that produced the values.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from station.diagnostics.effects import Context, get_effect, smooth_temperature
from station.diagnostics.fit import DutFit
from contracts.types import AXES, StationError, T_REF_C

MODEL_FORMAT = "station-diagnostic-model"
MODEL_VERSION = 1


@dataclass
class DiagnosticModel:
    """Baseline + effects with fitted values, per DUT (or per sensor type); saved as versioned JSON.

    compensate() inverts the model: returns the acceleration at 25 C (Acc0) in g.
    """

    serial: str
    effects: list[str]
    axes: dict[str, dict[str, float]]  # axis -> param name -> value (linear params, no acc0)
    nonlinear: dict[str, dict[str, float]]
    sigma: dict = field(default_factory=dict)
    t_ref_c: float = T_REF_C
    t_power_on_s: float = 0.0
    version: int = MODEL_VERSION

    @staticmethod
    def from_fit(serial: str, fit: DutFit, t_power_on_s: float = 0.0) -> "DiagnosticModel":
        axes, sigma = {}, {}
        for i, ax in enumerate(AXES):
            axes[ax] = {}
            sigma[ax] = {}
            for name, b, s in zip(fit.col_names[i], fit.beta[i], fit.beta_sigma[i]):
                if name.startswith("acc0_g["):
                    continue
                axes[ax][name] = float(b)
                sigma[ax][name] = float(s) if np.isfinite(s) else None
        sigma["nonlinear"] = fit.nl_sigma
        return DiagnosticModel(serial=serial, effects=list(fit.effects), axes=axes,
                               nonlinear={k: dict(v) for k, v in fit.nl.items()}, sigma=sigma,
                               t_power_on_s=t_power_on_s)

    def to_json(self) -> dict:
        return {"format": MODEL_FORMAT, "version": self.version, "serial": self.serial,
                "t_ref_c": self.t_ref_c, "t_power_on_s": self.t_power_on_s, "effects": self.effects,
                "axes": self.axes, "nonlinear": self.nonlinear, "sigma": self.sigma}

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_json(), indent=2) + "\n", encoding="utf-8")

    @staticmethod
    def from_json(obj: dict) -> "DiagnosticModel":
        if obj.get("format") != MODEL_FORMAT:
            raise StationError("not a station diagnostic model (format field missing)")
        if int(obj.get("version", 0)) > MODEL_VERSION:
            raise StationError(f"model version {obj.get('version')} is newer than this code ({MODEL_VERSION})")
        for e in obj["effects"]:
            get_effect(e)
        return DiagnosticModel(serial=obj.get("serial", ""), effects=list(obj["effects"]),
                               axes=obj["axes"], nonlinear=obj.get("nonlinear", {}),
                               sigma=obj.get("sigma", {}), t_ref_c=float(obj.get("t_ref_c", T_REF_C)),
                               t_power_on_s=float(obj.get("t_power_on_s", 0.0)),
                               version=int(obj.get("version", MODEL_VERSION)))

    @staticmethod
    def load(path: str | Path) -> "DiagnosticModel":
        p = Path(path)
        try:
            obj = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise StationError(f"{p}: cannot read model ({exc})") from None
        return DiagnosticModel.from_json(obj)

    def predict(self, time_s: np.ndarray, acc0_g: np.ndarray, temp_c: np.ndarray) -> np.ndarray:
        """Model output in g for true readings acc0_g (n, 3) at the measured temperatures."""
        time_s = np.asarray(time_s, np.float64)
        temp_c = np.asarray(temp_c, np.float64)
        acc0_g = np.asarray(acc0_g, np.float64).reshape(-1, 3)
        effects = [get_effect(n) for n in self.effects]
        t = temp_c
        for e in effects:
            t2 = e.temperature(t, time_s, self.nonlinear.get(e.name, {}))
            if t2 is not None:
                t = t2
        ctx = Context(time_s=time_s, temp_c=temp_c, temp_smooth_c=smooth_temperature(temp_c, time_s),
                      dt_c=t - self.t_ref_c, acc0_g=acc0_g, t_power_on_s=self.t_power_on_s, cache={})
        out = acc0_g * 1000.0
        for i, ax in enumerate(AXES):
            p = self.axes[ax]
            out[:, i] += ctx.dt_c * (p["tdb_mg_per_c"] + p["tdsf_ppm_per_c"] * acc0_g[:, i] * 1e-3)
        for e in effects:
            cols = e.columns(ctx, self.nonlinear.get(e.name, {}))
            for i, ax in enumerate(AXES):
                for m, ln in enumerate(e.linear):
                    out[:, i] += cols[:, i, m] * self.axes[ax].get(f"{e.name}.{ln}", 0.0)
        return out / 1000.0

    def compensate(self, time_s: np.ndarray, acc_g: np.ndarray, temp_c: np.ndarray) -> np.ndarray:
        """Acc0 (g, reading at 25 C without the modelled effects) from measured acc and temperature.

        Fixed-point inversion of predict(): the Acc0-dependent terms are ~1e-3 of Acc0, so a few
        passes converge.
        """
        acc_g = np.asarray(acc_g, np.float64).reshape(-1, 3)
        acc0 = acc_g.copy()
        for _ in range(6):
            acc0 = acc0 + (acc_g - self.predict(time_s, acc0, temp_c))
        return acc0



__all__ = ["DiagnosticModel", "MODEL_FORMAT", "MODEL_VERSION"]
