"""Shaping one DUT's calibration result from what its run collected (pure: a DutRun in, a typed
record out: contracts/run_records.py ThermalReport, contracts/sfem_result.py SfemResult).

Thermal: the offline fit (station/science/thermal_calibration.calibrate) over the run's samples at
its logged segments, beside the live streaming calibrator's own result, as `station calibrate
--json` prints it. SFEM: `station sfem`'s pipeline (station/science/sfem_record.py) on the run's
samples as its exported log holds them, so both give the same record (sensors2023). Both run in a
worker thread while the pump may still append blocks, so they work on a snapshot of the block list.
"""

from __future__ import annotations


import numpy as np

from contracts.json_safe import plain_json
from contracts.run_records import ThermalReport
from contracts.sfem_result import SfemResult
from contracts.logfile import ACC_DECIMALS, TEMP_DECIMALS, TIME_DECIMALS
from contracts.types import T_REF_C, SampleBlock
from station.daemon.dut_run import DutRun
from station.profiles import Profile
from station.science.sfem_record import fit_sfem_record
from station.science.thermal_calibration import calibrate, fit_samples


def thermal_result(d: DutRun, operating_range_c: float = 70.0) -> ThermalReport:
    """Streaming (the live calibrator) and offline results of one DUT, as `station calibrate --json`."""
    block = fit_samples(placed_samples(d), [s.t_end_s for s in d.segments])
    res = dict(calibrate(block, operating_range_c=operating_range_c))
    res["serial"] = d.serial
    try:
        if d.calibrator is None:
            raise ValueError("no live calibrator")
        res["streaming_live"] = d.calibrator.result().to_json()
    except Exception as exc:  # noqa: BLE001 - the live result is a comparison: its absence is said, not fatal
        res["streaming_live"] = {"error": str(exc)}
    res["n_samples"] = int(len(block))
    return ThermalReport.from_json(plain_json(res))


def placed_samples(d: DutRun) -> SampleBlock:
    """The DUT's samples that were placed at a step's position (station/science/placement.py):
    what a turn, a plate not yet settled or a plate at the wrong position measured is not fitted.
    Snapshots first (atomic copies under the GIL): the pump may still append in another thread."""
    blocks, positions = list(d.blocks), list(d.block_positions)
    return SampleBlock.concat([b for b, p in zip(blocks, positions) if p >= 0])


def run_log_arrays(d: DutRun) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every sample of the run with its placement label (-1: not placed), at the precision the
    database stores and `station db export` writes them (db/codec.py, contracts/logfile.py), so the
    SFEM of the live run and of its exported log see the very same numbers. Snapshots first."""
    pairs = list(zip(list(d.blocks), list(d.block_positions)))  # a block appended without its label yet: later
    full = SampleBlock.concat([b for b, _ in pairs])
    pos = np.concatenate([np.full(len(b), p, dtype=np.int64) for b, p in pairs]) if pairs \
        else np.zeros(0, dtype=np.int64)

    def stored(x: np.ndarray, decimals: int) -> np.ndarray:
        out: np.ndarray = np.rint(np.asarray(x, dtype=np.float64) * 10**decimals) / 10**decimals
        return out

    return (stored(full.time_s, TIME_DECIMALS), stored(full.acc_g, ACC_DECIMALS), stored(full.temp_c, TEMP_DECIMALS),
            pos)


def sfem_result(d: DutRun, profile: Profile) -> SfemResult:
    """The run's SFEM (sensors2023): exactly what `station sfem` computes from the run's exported
    log (station/science/sfem_record.py fit_sfem_record on the same samples and placement labels),
    with the profile's reference temperature and fixture setting, as the typed record
    contracts/sfem_result.py SfemResult. StationError when no step can be fitted."""
    time_s, acc_g, temp_c, position = run_log_arrays(d)
    rec = fit_sfem_record(time_s, acc_g, temp_c, None, position, ref_sigma_deg=profile.sfem_ref_sigma_deg,
                          t_ref_c=T_REF_C if profile.sfem_reference_temp_c is None else profile.sfem_reference_temp_c)
    return SfemResult.from_json(rec.to_json())  # the science's record as the one shape that travels
