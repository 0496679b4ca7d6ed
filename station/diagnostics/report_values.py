"""How fitted numbers appear in the diagnosis report: rounding, and the per-DUT parameter table
with 1-sigma uncertainties in physical units.

Why a module of its own: every part that writes into the report (the noise model, the gate, the
ranking) rounds the same way, so the JSON is stable and a NaN never leaks out (null instead); and
the parameter table is the one place where a TDSF the data cannot identify is reported as null
with the test that would identify it, never as a number with a sigma the data cannot support.
"""

from __future__ import annotations

import numpy as np

from station.diagnostics.design import tdsf_identifiable
from station.diagnostics.fit import DutFit
from station.diagnostics.segmentation import DutData
from contracts.types import AXES


def _r(x, nd=4):
    if x is None or not np.isfinite(x):
        return None
    return round(float(x), nd)


def _sig(x, n=6):
    """Round to n significant digits (parameters span 1e-4 mg/C^3 to 1e3 ppm/C)."""
    if x is None or not np.isfinite(x):
        return None
    return float(f"{float(x):.{n}g}")


TDSF_TEST = ("log a second orientation in which this axis reads a different Acc0 (turn the board over: "
             "+1 g and -1 g on the axis, e.g. the fast-thermal P/N turn or six-position) through the same "
             "temperatures; TDB and TDSF are then told apart by how the drift scales with Acc0")


def _params_json(data: list[DutData], fits: list[DutFit]) -> dict:
    """Fitted parameters with 1-sigma uncertainties in physical units, per DUT.

    Where TDSF is not identifiable (one orientation, or orientations with the same Acc0 on an axis)
    it is reported as null with the reason, and tdb_mg_per_c is the total drift of that orientation
    (also given as total_drift_mg_per_c): never a TDSF with a sigma that the data cannot support."""
    out = {}
    for d, f in zip(data, fits):
        dut: dict = {"baseline": {}, "effects": {}}
        tdsf_ok = tdsf_identifiable(f.acc0_g)
        for i, ax in enumerate(AXES):
            for name, b, s_ in zip(f.col_names[i], f.beta[i], f.beta_sigma[i]):
                entry = {"value": _sig(b), "sigma": _sig(s_, 3)}
                if "." in name:
                    eff, pname = name.split(".", 1)
                    if s_ == 0 and b == 0:
                        continue
                    dut["effects"].setdefault(eff, {}).setdefault(pname, {})[ax] = entry
                elif name == "tdsf_ppm_per_c" and not tdsf_ok[i]:
                    dut["baseline"].setdefault(name, {})[ax] = {
                        "value": None, "sigma": None, "identifiable": False,
                        "reason": "Acc0 of this axis is the same in every orientation of the log: only the total "
                                  "drift TDB + TDSF Acc0 is measured", "test_to_identify": TDSF_TEST}
                else:
                    dut["baseline"].setdefault(name, {})[ax] = entry
                    if name == "tdb_mg_per_c" and not tdsf_ok[i]:
                        dut["baseline"].setdefault("total_drift_mg_per_c", {})[ax] = dict(entry)
        for eff, vals in f.nl.items():
            for pname, v in vals.items():
                dut["effects"].setdefault(eff, {})[pname] = {
                    "value": _sig(v), "sigma": _sig(f.nl_sigma.get(eff, {}).get(pname, float("nan")), 3)}
        out[d.serial] = dut
    return out


__all__ = ["TDSF_TEST"]
