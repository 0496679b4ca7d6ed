"""Ended batches for the end-view tests (tests/test_browser_end_view.py): the rows a real batch
leaves, written through the real Database and DbWriter, each verdict decided by the real
station.decisions.verdicts.final_verdict against the built-in LIS3DSH limits from the figures of
a thermal result (so tray, grade and reason are the station's own words), and each fault reason
in the daemon's own wording (contracts.trace.label_mismatch, the intake's link-lost and stall
texts, the sequencer's plate and "cannot" texts). No simulated batch: fast, and the page is served
by the real app from these rows.

`OUTCOMES` names what a slot ends as; `write_ended_batch` writes one batch of them.
"""

from __future__ import annotations

from dataclasses import dataclass

from contracts.events import DutResult, DutVerdict, SegmentLogged, SlotStateChanged
from contracts.run_records import ThermalReport
from contracts.trace import Trace, label_mismatch
from db import Database, DbWriter
from db.models import DutRun
from records_support import segments_for
from station.decisions.limits import default_products
from station.decisions.verdicts import RunRecord, final_verdict

TRACE = Trace(work_order="WO-24-0815", part_number="ACC-3DSH-01", part_revision="C", lot="L2411-07")


def thermal(tdb=(0.2, -0.3, 0.4), tdsf=(-150.0, -120.0, -200.0), e_fs=0.3, bow=0.5, sig_tdsf=4.0) -> dict:
    """A thermal result in the shape the verdict reads (offline axes, streaming axes, residual)."""
    axes = {ax: {"tdb_mg_per_c": b, "tdsf_ppm_per_c": s, "tdb_sigma_mg_per_c": 0.01, "tdsf_sigma_ppm_per_c": sig_tdsf,
                 "tdsf_clamped": False} for ax, b, s in zip("xyz", tdb, tdsf)}
    residual = {ax: {"drift_error_fs_pct": e_fs, "drift_error_fs_sigma_pct": 0.01, "drift_error_mg": 6.0 * e_fs,
                     "bow_mg": bow, "bow_sigma_mg": 0.2, "ramp_residual_rms_mg": 0.3, "noise_ug_per_sqrt_hz": 380.0}
                for ax in "xyz"}
    return {"method": "offline", "axes": axes, "streaming": {"method": "streaming", "axes": axes},
            "residual": {"axes": residual}}


# what a slot ends as: (result or None, run end state, fault reason); serial placeholders {serial}
OUTCOMES: dict[str, tuple[dict | None, str, str]] = {
    "pass A": (thermal(), "done", ""),
    "pass B": (thermal(tdb=(1.2, 0.3, -0.2), e_fs=0.6), "done", ""),
    "marginal": (thermal(tdsf=(-150.0, -496.0, -200.0)), "done", ""),  # the interval crosses -500
    "fail TDB": (thermal(tdb=(1.62, 0.1, 0.2)), "done", ""),
    "fail TDSF": (thermal(tdsf=(-150.0, -120.0, -612.0)), "done", ""),
    "fail E_FS": (thermal(e_fs=1.4), "done", ""),
    "link lost": (None, "faulted", "serial /dev/pts/7: link lost: serial port /dev/pts/7 closed"),
    "no samples": (None, "faulted", "serial /dev/pts/9: no samples for 10.1 s"),
    "analysis": (None, "faulted", "analysis: offline: orientation 0 holds data more than 0.8 g apart"),
    "plate never arrived": (None, "faulted", "step 'N hot': plate never arrived at N: 412 s sample time after Done "
                                             "it faces P"),
    "cannot": (None, "faulted", "Ana (token line-3 kiosk) could not turn the plate to N: plate jammed against the "
                                "lamp bracket"),
    "label": (None, "faulted", "{label}"),
}


@dataclass
class Slot:
    slot: str
    outcome: str  # a key of OUTCOMES
    serial: str = ""
    label: str | None = None  # the label serial scanned ("label": another part's)


def write_ended_batch(db: Database, slots: list[Slot], *, trace: Trace = TRACE, state: str = "finished",
                      operator: str = "Ana", profile: str = "fast-thermal", reason: str | None = None) -> dict:
    """One ended batch of `slots`; returns {"batch": id, "slots": {slot: {serial, verdict, tray, reason, run,
    attempt}}}. A slot's serial defaults to SIM<its number>: a later batch with the same slots retests them."""
    spec = default_products()["LIS3DSH"]
    labels = {s.slot: s.label for s in slots if s.label}
    batch = db.create_batch(profile, operator, {"name": db.station}, state="running",
                            trace=Trace(**trace.fields(), labels=labels))
    out: dict = {"batch": batch, "slots": {}}
    w = DbWriter(db, interval_s=0.02)
    try:
        for s in slots:
            serial = s.serial or f"SIM{int(''.join(c for c in s.slot if c.isdigit()) or 0):04d}"
            result, end_state, why = OUTCOMES[s.outcome]
            if s.outcome == "label":
                why = label_mismatch(s.label or "SIM9999", serial) or ""
            # as the daemon does (station/daemon/slots.py): a label mismatch is no attempt of the board's serial
            run = db.create_run(batch, s.slot, serial, "LIS3DSH", {"serial": serial, "sensor": "LIS3DSH"},
                                counts_as_attempt=s.outcome != "label")
            with db.session() as ss:
                attempt = ss.get(DutRun, run).attempt
            w.bind_run(batch, s.slot, run)
            if result is not None:
                tdb = tuple(result["axes"][ax]["tdb_mg_per_c"] for ax in "xyz")
                tdsf = tuple(result["axes"][ax]["tdsf_ppm_per_c"] for ax in "xyz")
                for sg in segments_for(tdb, tdsf):
                    w.submit(SegmentLogged(batch, s.slot, serial, 0, sg))
                stored = {"offline": {"method": "offline", "n_segments": 8, "axes": result["axes"]},
                          "streaming": {"method": "streaming", "n_segments": 8, "axes": result["axes"]}}
                w.submit(DutResult(batch, s.slot, serial, thermal=ThermalReport.from_json(stored)))
            w.submit(SlotStateChanged(batch, s.slot, serial, end_state, fault_reason=why))
            # the verdict's reason as the daemon gives it (station/decisions/moment.py end_of): "faulted: <why>"
            end_reason = f"faulted: {why}" if end_state == "faulted" else why
            v = final_verdict(RunRecord("thermal", False, end_state, end_reason, result, {"samples_lost": 0}, 2000), spec)
            verdict = {**v.to_json(), "attempt": attempt, "run_id": run}
            w.submit(DutVerdict(batch, s.slot, serial, verdict=verdict))
            out["slots"][s.slot] = {"serial": serial, "verdict": v.verdict, "tray": v.tray, "reason": v.reason,
                                    "run": run, "attempt": attempt}
        assert w.flush(30)
    finally:
        w.close()
    db.set_batch_state(batch, state, reason=reason)
    return out


def mixed_slots() -> list[Slot]:
    """12 slots: 6 pass (4 grade A, 2 grade B), 2 marginal, 2 fail, a lost link and a label mismatch."""
    kinds = ["pass A", "pass A", "label", "pass B", "marginal", "fail TDSF", "pass A", "link lost", "pass A",
             "marginal", "pass B", "fail TDB"]
    return [Slot(f"s{i + 1:02d}", k, label="SIM9999" if k == "label" else None) for i, k in enumerate(kinds)]


def nothing_passed_slots() -> list[Slot]:
    """11 DUTs, none passes: the issue's "0 of 11" batch, which still ends 'finished'."""
    kinds = ["fail TDB", "marginal", "fail TDSF", "no samples", "fail E_FS", "analysis", "fail TDB", "marginal",
             "plate never arrived", "fail TDSF", "fail TDB"]
    return [Slot(f"s{i + 1:02d}", k) for i, k in enumerate(kinds)]


def twelve_exceptions_slots() -> list[Slot]:
    """12 slots, none passed, six different errors: the most the kiosk's end view must hold."""
    kinds = ["no samples", "analysis", "link lost", "label", "plate never arrived", "cannot", "fail TDB", "fail TDSF",
             "fail E_FS", "marginal", "marginal", "marginal"]
    return [Slot(f"s{i + 1:02d}", k, label="SIM9999" if k == "label" else None) for i, k in enumerate(kinds)]


__all__ = ["TRACE", "OUTCOMES", "Slot", "thermal", "write_ended_batch", "mixed_slots", "nothing_passed_slots",
           "twelve_exceptions_slots"]
