"""Program and verify after an SFEM profile (issue 42): the station's thermal SFEM on the board as its
version-2 record (docs/design.md 3.1), read back, applied and verified.

program_verify.py hands an SFEM profile's two halves here (same ProgramHost, same events, same
conventions: a failed write, read-back or switch faults that DUT alone with the named reason and
its verdict is error; a failed verification fails its axes through `verify_failed_axes`):

  program_sfem_duts   the program step, after the SFEM analysis: per live DUT in parallel, for a
                      board whose identity reports `sfem3`: the cubic record built from the station's
                      SfemThermalModel (station/science/sfem_board_record.py), the stream stopped,
                      the identity read again, the record written ($SFTW x4 + $SFTC: the board's CRC
                      must be the station's), read back ($SFTR: every float32 and the CRC equal),
                      compensation switched on and confirmed ($COMP,1, `C` reply comp=1), the stream
                      started again, now compensated. A board without `sfem3` (version 1 only) is
                      NOT programmed: its program record says so (`not_applicable`), nothing else
                      of its run changes (its verdict is the SFEM run's).
  verify_sfem_duts    at the batch's end, like eq. 13's verification: while the board streamed its
                      compensated output over the temperatures the plate went through after
                      programming (the profile's cool-down), that output against the station's
                      prediction. The plate is static at the last SFEM position, so the prediction
                      is that position's gravity as the station's model maps it: the mean of
                      model.compensate(raw, T) over the position's samples just before programming.
                      Block means (BLOCK_S) of the output minus it, per axis: rms and max in mg,
                      against limits from the fit's own figures (`_sigma_terms`): K_RMS (K_MAX) x
                      sigma + the record's own approximation error + one output count.

The output is judged only where the board applies the record as fitted: samples whose temperature
lies outside the record's range (the board clamps there) are counted and left out.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Protocol, TypeVar

import numpy as np

from contracts.events import DutProgrammed, DutVerified, EventBus
from contracts.json_safe import JsonDict, finite_or_none, plain_json_dict
from contracts.run_records import ProgramRecord
from contracts.sfem_cubic import SfemCubicRecord
from contracts.sfem_result import SfemResult
from contracts.types import AXES, SampleBlock
from drivers.base import BoardDriver, CalibrationError, DriverError
from station.daemon.dut_run import DutRun
from station.daemon.sequencer import Sequencer
from station.decisions.board_checks import SFEM_CUBIC_KIND
from station.science.bias_wander import wander_for
from station.science.offline_fit import temperature_quantum_c
from station.science.sfem_board_record import cubic_record, thermal_model_of
from station.science.sfem_model import SfemInsufficientData
from station.science.sfem_thermal import SfemParams, SfemThermalModel

log = logging.getLogger(__name__)

METHOD = SFEM_CUBIC_KIND  # ProgramRecord.method and the verification's kind
BLOCK_S = 10.0  # block means of the compensated output (the verification judges these, not single samples)
K_RMS, K_MAX = 3.0, 4.0  # limits in sigmas: the rms of the block residuals, their largest
MIN_BLOCKS = 3


class SfemHost(Protocol):
    """What the SFEM's program and verify need of the station (program_verify.ProgramHost's shape)."""

    bus: EventBus

    def driver_of(self, slot: str) -> BoardDriver | None: ...

    async def board_changed(self, d: DutRun, when: str) -> str | None: ...

    def fault_dut(self, seq: Sequencer, d: DutRun, reason: str) -> None: ...


Quiesce = Callable[[BoardDriver], Awaitable[bool]]


def record_json(rec: SfemCubicRecord) -> JsonDict:
    return {"t_ref_c": rec.t_ref_c, "t_lo_c": rec.t_lo_c, "t_hi_c": rec.t_hi_c, "coef": [list(r) for r in rec.coef],
            "crc": f"{rec.crc32():08X}",
            "layout": "coef[k][0..11] = power k of (T - t_ref_c) for a11..a33 (row by row), b_x, b_y, b_z in g"}


T = TypeVar("T")


async def _tries(drv: BoardDriver, step: Callable[[], Awaitable[T]], retries: list[str], label: str) -> tuple[T, int]:
    """step() up to the driver's cal_retries times: drivers/base.py BoardDriver._retried, the very
    policy program_thermal uses (a CalibrationError is noted and retried, "unsupported" at once)."""
    result: tuple[T, int] = await drv._retried(step, retries, label, f"{label}failed")
    return result


async def write_and_confirm(drv: BoardDriver, rec: SfemCubicRecord) -> tuple[int, SfemCubicRecord, int, list[str]]:
    """Write the record, read it back (CRC and every float32 equal), switch compensation on and
    confirm it. Returns (crc, read back, attempts of the write, retries); CalibrationError otherwise."""
    want = rec.to_f32()
    want_crc = want.crc32()
    retries: list[str] = []

    async def write_and_read_back() -> SfemCubicRecord:
        board_crc = await drv.write_sfem_cubic(want)
        if board_crc != want_crc:
            raise CalibrationError("crc_mismatch", f"board stored CRC {board_crc:08X}, station computed {want_crc:08X}")
        rb = await drv.read_sfem_cubic()
        if rb.to_f32() != want or rb.crc32() != want_crc:
            raise CalibrationError("readback_mismatch", f"read back CRC {rb.crc32():08X} differs from the written "
                                   f"{want_crc:08X} or its values do")
        return rb

    async def compensation_on() -> bool:
        await drv.set_compensation(True)
        if not (await drv.read_thermal()).comp:
            raise CalibrationError("comp_not_set", "compensation still off after COMP 1")
        return True

    rb, attempt = await _tries(drv, write_and_read_back, retries, "")
    await _tries(drv, compensation_on, retries, "compensation ")
    return want_crc, rb, attempt, retries


async def program_sfem_duts(station: SfemHost, seq: Sequencer, quiesce: Quiesce) -> None:
    """The program step of an SFEM profile (module doc)."""

    def publish(d: DutRun, rec: ProgramRecord) -> None:
        d.program = rec
        station.bus.publish(DutProgrammed(seq.batch_id, slot=d.slot, serial=d.serial or "", program=rec))

    async def one(d: DutRun) -> None:
        drv = station.driver_of(d.slot)
        if drv is not None and not drv.supports_sfem_cubic:
            caps = "+".join(sorted(drv.identity.caps)) if drv.identity is not None and drv.identity.caps else "none"
            publish(d, ProgramRecord(False, method=METHOD, readback={
                "not_applicable": True,
                "sfem_cubic": f"not programmed: the board stores no version-2 record (caps: {caps}; 'sfem3' needed): "
                              "its run is judged as an SFEM run without program and verify"}))
            return
        model = thermal_model_of(d.result.thermal) if isinstance(d.result, SfemResult) else None
        try:
            if model is None:
                raise SfemInsufficientData("no SFEM thermal model (one temperature step, or no SFEM result)")
            rec, approx = cubic_record(model)
        except SfemInsufficientData as exc:
            publish(d, ProgramRecord(False, method=METHOD, error_kind="no_result", error=str(exc)))
            station.fault_dut(seq, d, f"program: nothing to write: {exc}")
            return
        written: JsonDict = {"sfem_cubic": record_json(rec), "approximation": approx.to_json()}
        if drv is None:
            publish(d, ProgramRecord(False, method=METHOD, error_kind="link", error=f"{d.link}: link closed",
                                     readback=written))
            station.fault_dut(seq, d, f"program: link: {d.link}: link closed")
            return
        await quiesce(drv)
        changed = await station.board_changed(d, "before programming")
        if changed is not None:
            publish(d, ProgramRecord(False, method=METHOD, error_kind="identity", error=changed, readback=written))
            station.fault_dut(seq, d, f"program: not written: {changed}")
            return
        try:
            crc, _rb, attempts, retries = await write_and_confirm(drv, rec)
        except CalibrationError as exc:
            publish(d, ProgramRecord(False, method=METHOD, error_kind=exc.kind, error=str(exc), attempts=exc.attempts,
                                     comp=False, readback=written))
            station.fault_dut(seq, d, f"program: {exc.kind}: {exc}")
            return
        except DriverError as exc:
            publish(d, ProgramRecord(False, method=METHOD, error_kind="link", error=str(exc), comp=False,
                                     readback=written))
            station.fault_dut(seq, d, f"program: link: {exc}")
            return
        info = ProgramRecord(True, method=METHOD, attempts=attempts, comp=True, readback={
            **written, "crc": f"{crc:08X}", "readback_crc": f"{crc:08X}", "readback_identical": True,
            "retries": retries, "comp_from_t": drv.last_sample_t})
        try:
            await drv.start()  # streaming again, now compensated by the cubic SFEM
        except DriverError as exc:
            publish(d, info)
            station.fault_dut(seq, d, f"program: restart after programming failed: {exc}")
            return
        if retries:
            log.warning("batch %d slot %s: cubic SFEM written after retries: %s", seq.batch_id, d.slot, "; ".join(retries))
        publish(d, info)

    await asyncio.gather(*(one(d) for d in seq.duts if d.live))


# ---- the verification ------------------------------------------------------------------------------
@dataclass(frozen=True)
class VerifyInput:
    """What one DUT's verification reads (snapshots taken on the loop, worked on in a thread)."""

    blocks: list[tuple[SampleBlock, int, int]]  # (block, step index, position: -1 not placed)
    program_index: int
    position: int  # where the plate sits during the verification (the last SFEM position)
    comp_from_t: float | None  # board time (run's time base) from which samples are compensated
    settle_s: float
    model: SfemThermalModel
    t_lo_c: float
    t_hi_c: float
    approx_mg: float
    lsb_mg: float
    odr_hz: float
    sensor: str
    step_sigmas: dict[str, np.ndarray] | None = None  # each parameter's sigma per step (step_sigmas), coldest first


def _block_means(block: SampleBlock, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    k = len(block) // n
    cut = k * n
    return (block.time_s[:cut].reshape(k, n).mean(axis=1), block.acc_g[:cut].reshape(k, n, 3).mean(axis=1),
            block.temp_c[:cut].reshape(k, n).mean(axis=1))


def _white_sigma_g(acc: np.ndarray) -> np.ndarray:
    """Per-sample white noise per axis: first differences / sqrt 2 (a slow drift does not count)."""
    if len(acc) < 3:
        return np.zeros(3)
    out: np.ndarray = np.std(np.diff(acc, axis=0), axis=0) / math.sqrt(2.0)
    return out


def step_sigmas(result: SfemResult) -> dict[str, np.ndarray]:
    """Each SFEM parameter's 1-sigma per temperature step (n_steps, 3), coldest first (the thermal
    model's order): what the fit of each step says of its own parameters (SfemFit.to_json)."""
    def vec(v: object) -> np.ndarray:
        arr = np.asarray(v if isinstance(v, (list, tuple)) and len(v) == 3 else [np.nan] * 3, dtype=np.float64)
        return np.nan_to_num(arr, nan=0.0)

    rows: dict[str, list[np.ndarray]] = {name: [] for name in SfemThermalModel.NAMES}
    for st in result.steps:
        d = st.detail
        mis, non = d.get("misalignment"), d.get("nonorthogonality")
        rows["rotvec_rad"].append(np.radians(vec(mis.get("rotvec_sigma_deg"))) if isinstance(mis, dict) else vec(None))
        rows["alpha"].append(vec(non.get("sigma_rad")) if isinstance(non, dict) else vec(None))
        rows["scale"].append(vec(d.get("scale_sigma")))
        rows["b"].append(vec(d.get("bias_sigma")))
    return {name: np.array(v).reshape(-1, 3) for name, v in rows.items()}


def _sigma_terms(v: VerifyInput, p: np.ndarray, t_p: float, temps: np.ndarray, span_s: float,
                 sigma_out: np.ndarray, n_block: int, sigma_p: np.ndarray, n_p: int) -> dict[str, np.ndarray]:
    """1-sigma (g) per axis of a block's residual from the station's own figures:
    model     the steps' own parameter sigmas through the thermal model's polynomial: the error of
              [output at T - output at the prediction's T_p] for the raw reading that the model maps
              to the prediction, sum_s sigma_s^2 (l_s(T) g(T) - l_s(T_p) g(T_p))^2 with l_s the
              least-squares weights of step s at T and g the output's sensitivity to the parameter
              (the largest over the verified temperatures); without the steps' sigmas, each
              polynomial coefficient moved by its own sigma (correlations ignored: an over-statement)
    misfit    the steps' scatter about each parameter's polynomial (residual_rms), at both ends
    noise     the block means' and the prediction's own white noise
    wander    the sensor class's bias wander over the run (from its first SFEM sample to the last
              verified block: what the bias polynomial took in from the steps and what moved since)
    quantiser the board's temperature reading in steps: the board compensates with the stepped T
              while the sensor drifts with the true one (raw drift per C x step / sqrt 12)"""
    m = v.model
    grid = np.unique(np.concatenate([np.linspace(float(temps.min()), float(temps.max()), 7), [t_p]]))

    def raw_for_p(t: float) -> np.ndarray:
        base = m.params_at(t)
        raw: np.ndarray = np.linalg.solve(base.A, p) + base.b  # the raw reading the model maps to p at t
        return raw

    def sensitivity(t: float, name: str, j: int, h: float = 1e-6) -> np.ndarray:
        base = m.params_at(t)
        vals = {k: np.array(getattr(base, k), dtype=np.float64) for k in m.NAMES}
        vals[name][j] += h
        moved = SfemParams(vals["rotvec_rad"], vals["alpha"], vals["scale"], vals["b"])
        u = raw_for_p(t)
        out: np.ndarray = (moved.A @ (u - moved.b) - p) / h
        return out

    model_var = np.zeros(3)
    sig_steps = v.step_sigmas
    if sig_steps is not None and all(sig_steps[n].shape == (len(m.temps_c), 3) for n in m.NAMES):
        lmap = np.linalg.pinv(np.polynomial.polynomial.polyvander(m.temps_c - m.t_ref_c, m.degree))

        def weights(t: float) -> np.ndarray:
            w: np.ndarray = np.polynomial.polynomial.polyvander(np.array([t - m.t_ref_c]), m.degree)[0] @ lmap
            return w

        w_p = weights(t_p)
        for name in m.NAMES:
            for j in range(3):
                g_p = sensitivity(t_p, name, j)
                worst = np.zeros(3)
                for t in grid:
                    diff = np.outer(weights(float(t)), sensitivity(float(t), name, j)) - np.outer(w_p, g_p)  # (n_steps, 3)
                    worst = np.maximum(worst, np.sum((sig_steps[name][:, j:j + 1] * diff) ** 2, axis=0))
                model_var += worst
    else:
        for name in m.NAMES:
            sig = m.coef_sigma.get(name)
            if sig is None or sig.shape != m.coef[name].shape:
                continue
            for power in range(m.degree + 1):
                for j in range(3):
                    s = float(sig[power, j])
                    if not (s > 0 and math.isfinite(s)):
                        continue
                    coef = {k: c.copy() for k, c in m.coef.items()}
                    coef[name][power, j] += s
                    moved_m = SfemThermalModel(m.degree, coef, m.temps_c, m.misalignment_determined, m.t_ref_c)
                    changes = []
                    for t in grid:
                        a_t, a_p = moved_m.params_at(float(t)), moved_m.params_at(t_p)
                        changes.append(a_t.A @ (raw_for_p(float(t)) - a_t.b) - a_p.A @ (raw_for_p(t_p) - a_p.b))
                    model_var += np.max(np.array(changes) ** 2, axis=0)
    misfit_var = np.zeros(3)
    for name in m.NAMES:
        rms = m.residual_rms.get(name)
        if rms is not None and rms.shape == (3,):
            for j in range(3):
                r = float(rms[j])
                if r > 0 and math.isfinite(r):
                    misfit_var += 2.0 * (sensitivity(t_p, name, j) * r) ** 2  # at the verified temperature and at T_p
    # raw drift per C at the position (the model's inverse): what the board's stepped temperature misses
    mid = 0.5 * (float(temps.min()) + float(temps.max()))
    du_dt = np.abs(raw_for_p(mid + 0.5) - raw_for_p(mid - 0.5))
    wander = wander_for(v.sensor)
    return {
        "model": np.sqrt(model_var),
        "misfit": np.sqrt(misfit_var),
        "noise": np.sqrt(sigma_out ** 2 / max(n_block, 1) + sigma_p ** 2 / max(n_p, 1)),
        "wander": np.full(3, math.sqrt(float(wander.structure_g2(span_s)))),
        "drift_per_c": du_dt,  # g/C: the caller multiplies by the reading's step / sqrt 12
    }


def verify_one(v: VerifyInput) -> JsonDict:
    """Pure part of one DUT's verification (module doc), in a worker thread."""
    flags: list[str] = []
    # the prediction: the position's samples just before programming (its last step there)
    before = [(b, st) for b, st, pos in v.blocks if st < v.program_index and pos == v.position and len(b)]
    if not before:
        return {"kind": METHOD, "passed": False, "axes": {},
                "flags": ["no samples of the plate's position before programming: nothing to predict the output with"]}
    last_step = max(st for _, st in before)
    pre = SampleBlock.concat([b for b, st in before if st == last_step])
    mapped = v.model.compensate(pre.acc_g, pre.temp_c)
    p = mapped.mean(axis=0)
    t_p = float(np.mean(pre.temp_c))
    # the window: compensated samples after the restart + settle, within the record's range
    after = SampleBlock.concat([b for b, st, _ in v.blocks if st >= v.program_index and len(b)])
    t0 = (v.comp_from_t if v.comp_from_t is not None else -math.inf) + v.settle_s
    keep = after.time_s > t0
    in_range = (after.temp_c >= v.t_lo_c) & (after.temp_c <= v.t_hi_c)
    n_outside = int(np.sum(keep & ~in_range))
    keep &= in_range
    win = SampleBlock(after.time_s[keep], after.acc_g[keep], after.temp_c[keep])
    n_block = max(1, int(round(BLOCK_S * v.odr_hz)))
    if len(win) < MIN_BLOCKS * n_block:
        return {"kind": METHOD, "passed": False, "axes": {}, "n_samples": len(win), "n_outside_range": n_outside,
                "flags": [f"only {len(win)} compensated samples within the record's range "
                          f"{v.t_lo_c:.1f}..{v.t_hi_c:.1f} C after programming: not verified"]}
    t_b, acc_b, temp_b = _block_means(win, n_block)
    resid_mg = (acc_b - p) * 1e3
    rms = np.sqrt(np.mean(resid_mg ** 2, axis=0))
    mx = np.max(np.abs(resid_mg), axis=0)
    t_first = min(float(b.time_s[0]) for b, st, _ in v.blocks if st < v.program_index and len(b))
    terms = _sigma_terms(v, p, t_p, temp_b, float(t_b[-1] - t_first), _white_sigma_g(win.acc_g), n_block,
                         _white_sigma_g(pre.acc_g), len(pre))
    q = temperature_quantum_c(win.temp_c)
    terms["quantiser"] = terms.pop("drift_per_c") * q / math.sqrt(12.0)
    sigma_mg = np.sqrt(sum(t ** 2 for t in terms.values())) * 1e3
    span = (float(temp_b.min()), float(temp_b.max()))
    if span[1] - span[0] < 5.0:
        flags.append(f"the plate moved only {span[1] - span[0]:.1f} C after programming: the thermal model is "
                     "hardly exercised")
    axes: dict[str, object] = {}
    for k, ax in enumerate(AXES):
        lim_rms = K_RMS * sigma_mg[k] + v.approx_mg + v.lsb_mg
        lim_max = K_MAX * sigma_mg[k] + v.approx_mg + v.lsb_mg
        ok = bool(rms[k] <= lim_rms and mx[k] <= lim_max)
        if not ok:
            flags.append(f"{ax}: residual rms {rms[k]:.3g} mg / max {mx[k]:.3g} mg over the limits "
                         f"{lim_rms:.3g} / {lim_max:.3g} mg")
        axes[ax] = {"passed": ok, "residual_rms_mg": float(rms[k]), "residual_max_mg": float(mx[k]),
                    "residual_mean_mg": float(np.mean(resid_mg[:, k])), "limit_rms_mg": float(lim_rms),
                    "limit_max_mg": float(lim_max), "sigma_mg": float(sigma_mg[k]),
                    "terms_mg": {name: float(t[k] * 1e3) for name, t in terms.items()}}
    passed = all(bool(a["passed"]) for a in axes.values() if isinstance(a, dict))
    return plain_json_dict({
        "kind": METHOD, "passed": passed, "flags": flags, "axes": axes,
        "prediction_g": p.tolist(), "prediction_temp_c": t_p,
        "prediction_from": f"{len(pre)} samples at position {v.position} (step {last_step}) mapped by the station's "
                           "SFEM thermal model",
        "temp_range_c": list(span), "record_range_c": [v.t_lo_c, v.t_hi_c], "n_samples": len(win),
        "n_outside_range": n_outside, "n_blocks": int(len(t_b)), "block_s": n_block / v.odr_hz,
        "window_s": [float(win.time_s[0]), float(win.time_s[-1])], "approx_error_mg": v.approx_mg,
        "k_rms": K_RMS, "k_max": K_MAX,
        "residual_blocks": {"temp_c": temp_b.tolist(), **{ax: resid_mg[:, k].tolist() for k, ax in enumerate(AXES)}},
    })


async def verify_sfem_duts(station: SfemHost, seq: Sequencer) -> None:
    """The verification of every DUT programmed with the cubic SFEM (module doc); a DUT whose
    verification cannot be judged gets passed=False with the reason, never a silent pass."""
    profile = seq.profile
    program_index = profile.program_step
    if program_index is None or program_index + 1 >= len(profile.steps):
        return
    verify_step = profile.steps[program_index + 1]

    async def one(d: DutRun) -> None:
        prog = d.program
        if prog is not None and prog.readback.get("not_applicable") is True:
            return  # a version-1 board: not programmed, nothing to verify (its run is the SFEM run's)
        out: JsonDict
        if prog is None or not prog.programmed:
            out = {"kind": METHOD, "passed": False, "axes": {},
                   "flags": ["no programming record for this run in this session: not verified"]}
        else:
            model = thermal_model_of(d.result.thermal) if isinstance(d.result, SfemResult) else None
            rec_doc = prog.readback.get("sfem_cubic")
            approx_doc = prog.readback.get("approximation")
            t_lo = finite_or_none(rec_doc.get("t_lo_c")) if isinstance(rec_doc, dict) else None
            t_hi = finite_or_none(rec_doc.get("t_hi_c")) if isinstance(rec_doc, dict) else None
            approx = finite_or_none(approx_doc.get("max_output_error_mg")) if isinstance(approx_doc, dict) else None
            if model is None or t_lo is None or t_hi is None or d.identity is None:
                out = {"kind": METHOD, "passed": False, "axes": {},
                       "flags": ["the station's SFEM model or the written record is missing: not verified"]}
            else:
                comp_t = prog.comp_from_t
                inp = VerifyInput(list(zip(list(d.blocks), list(d.block_steps), list(d.block_positions))), program_index,
                                  verify_step.position, None if comp_t is None else comp_t + d.time_offset_s,
                                  verify_step.settle_s, model, t_lo, t_hi, approx or 0.0,
                                  d.identity.ug_per_lsb / 1e3, d.identity.odr_hz, d.identity.sensor,
                                  step_sigmas(d.result) if isinstance(d.result, SfemResult) else None)
                try:
                    out = await asyncio.to_thread(verify_one, inp)
                except (ValueError, np.linalg.LinAlgError) as exc:
                    out = {"kind": METHOD, "passed": False, "axes": {},
                           "flags": [f"verification could not be computed: {exc}"]}
        d.verification = out
        if not out.get("passed"):
            log.warning("batch %d slot %s: cubic SFEM verification failed: %s", seq.batch_id, d.slot, out.get("flags"))
        station.bus.publish(DutVerified(seq.batch_id, slot=d.slot, serial=d.serial or "", verification=out))

    await asyncio.gather(*(one(d) for d in seq.duts if d.live))


__all__ = ["program_sfem_duts", "verify_sfem_duts", "verify_one", "VerifyInput", "write_and_confirm", "METHOD",
           "BLOCK_S", "K_RMS", "K_MAX", "step_sigmas"]
