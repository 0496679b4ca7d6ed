"""Database contents for the records tests (certificate, audit, SPC): batches of judged DUT runs
written through the real Database and DbWriter (no simulated batch: fast), with segments that
follow the thermal model so a certificate's fit plot has points on its lines."""

from __future__ import annotations

import random

from db import Database, DbWriter
from contracts.events import DutResult, DutVerdict, SegmentLogged, SlotStateChanged
from contracts.types import Segment

LIMITS = {"tdb_mg_per_c": 1.5, "tdsf_ppm_per_c": 500.0}


def thermal_result(tdb: tuple[float, float, float], tdsf: tuple[float, float, float]) -> dict:
    axes = {ax: {"tdb_mg_per_c": b, "tdsf_ppm_per_c": s, "tdb_sigma_mg_per_c": 0.01 + 0.005 * i,
                 "tdsf_sigma_ppm_per_c": 3.0 + i, "tdsf_clamped": False}
            for i, (ax, b, s) in enumerate(zip("xyz", tdb, tdsf))}
    return {"offline": {"method": "offline", "n_segments": 8, "axes": axes},
            "streaming": {"method": "streaming", "n_segments": 8, "axes": axes}}


def verdict_of(tdb, tdsf, attempt: int = 1) -> dict:
    checks = []
    worst = "pass"
    for ax, b, s in zip("xyz", tdb, tdsf):
        for name, v, lim, unit in (("tdb_mg_per_c", b, LIMITS["tdb_mg_per_c"], "mg/C"), ("tdsf_ppm_per_c", s, LIMITS["tdsf_ppm_per_c"], "ppm/C")):
            outcome = "pass" if abs(v) <= lim else "fail"
            if outcome == "fail":
                worst = "fail"
            checks.append({"measurement": name, "axis": ax, "value": v, "sigma": 0.01, "unit": unit, "low": -lim,
                           "high": lim, "outcome": outcome, "reason": ""})
    fails = [c for c in checks if c["outcome"] == "fail"]
    return {"verdict": worst, "grade": "A" if worst == "pass" else "reject", "tray": "T-A" if worst == "pass" else "T-reject",
            "reason": "; ".join(f"{c['axis']} {c['measurement']} {c['value']:.4g} {c['unit']}, limit {c['high']:g}" for c in fails),
            "attempt": attempt, "limits_name": "LIS3DSH", "limits_version": "2026-11", "checks": checks}


def segments_for(tdb, tdsf, temps=(25.0, 32.0, 39.0, 46.0)) -> list[Segment]:
    """Two orientations (+0.577 g, -0.577 g per axis) at each temperature, on eq. 1."""
    out = []
    k = 0
    for orient, a0 in ((0, 0.577), (1, -0.577)):
        for t in temps:
            dt = t - 25.0
            acc = tuple(a0 * (1 + s * 1e-6 * dt) + b * 1e-3 * dt for b, s in zip(tdb, tdsf))
            out.append(Segment(index=k, orientation=orient, n_samples=500, t_start_s=100.0 * k, t_end_s=100.0 * k + 80,
                               acc_mean_g=acc, acc_std_g=(1e-4, 1e-4, 1e-4), temp_mean_c=t, temp_std_c=0.2, position=orient))
            k += 1
    return out


def write_batches(db: Database, n_batches: int = 3, per_batch: int = 6, seed: int = 3, operator: str = "alice",
                  serial_prefix: str = "SN") -> list[dict]:
    """n_batches finished batches of per_batch judged DUTs (some fail); returns what was written."""
    rng = random.Random(seed)
    written = []
    w = DbWriter(db, interval_s=0.02)
    for b in range(n_batches):
        batch = db.create_batch("fast-thermal", operator, {"name": db.station}, state="running")
        for i in range(per_batch):
            slot = f"s{i + 1:02d}"
            serial = f"{serial_prefix}{b:02d}{i:02d}"
            run = db.create_run(batch, slot, serial, "LIS3DSH",
                                {"serial": serial, "sensor": "LIS3DSH", "fw": "2.3.1", "odr_hz": 3.125})
            w.bind_run(batch, slot, run)
            tdb = tuple(round(rng.gauss(0.3 + 0.05 * i, 0.35), 4) for _ in range(3))
            tdsf = tuple(round(rng.gauss(-120.0, 90.0), 1) for _ in range(3))
            if b % 2 == 1 and i >= per_batch - 2:  # every other batch: its last two boards fail (TDB x)
                tdb = (1.8 + 0.1 * i,) + tdb[1:]
            for sg in segments_for(tdb, tdsf):
                w.submit(SegmentLogged(batch, slot, serial, 0, sg))
            v = verdict_of(tdb, tdsf)
            w.submit(DutResult(batch, slot, serial, thermal=thermal_result(tdb, tdsf)))
            w.submit(SlotStateChanged(batch, slot, serial, "done"))
            w.submit(DutVerdict(batch, slot, serial, verdict=v))  # the final verdict: the MES record (design 8)
            written.append({"batch": batch, "run": run, "serial": serial, "slot": slot, "tdb": tdb, "tdsf": tdsf,
                            "verdict": v["verdict"]})
        w.flush()
        db.set_batch_state(batch, "finished")
    w.close()
    return written


def write_unjudged(db: Database, serial: str = "NORESULT1") -> int:
    batch = db.create_batch("fast-thermal", "bob", {}, state="running")
    return db.create_run(batch, "s01", serial, "LIS3DSH", {"serial": serial})


__all__ = ["write_batches", "write_unjudged", "segments_for", "verdict_of", "thermal_result", "DutVerdict"]
