"""Database contents for the records tests (certificate, audit, SPC): batches of judged DUT runs
written through the real Database and DbWriter (no simulated batch: fast), with segments that
follow the thermal model so a certificate's fit plot has points on its lines."""

from __future__ import annotations

import random

from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone

from sqlalchemy import update

from db import Database, DbWriter
from db.models import DutRun
from contracts.events import DutResult, DutVerdict, SegmentLogged, SlotStateChanged
from contracts.run_records import ThermalReport
from contracts.trace import Trace
from contracts.types import Segment

LIMITS = {"tdb_mg_per_c": 1.5, "tdsf_ppm_per_c": 500.0}


def thermal_result(tdb: tuple[float, float, float], tdsf: tuple[float, float, float]) -> dict:
    axes = {ax: {"tdb_mg_per_c": b, "tdsf_ppm_per_c": s, "tdb_sigma_mg_per_c": 0.01 + 0.005 * i,
                 "tdsf_sigma_ppm_per_c": 3.0 + i, "tdsf_clamped": False}
            for i, (ax, b, s) in enumerate(zip("xyz", tdb, tdsf))}
    return {"offline": {"method": "offline", "n_segments": 8, "axes": axes},
            "streaming": {"method": "streaming", "n_segments": 8, "axes": axes}}


def verdict_of(tdb, tdsf, attempt: int = 1, limits: dict | None = None, limits_name: str = "LIS3DSH",
               limits_version: str = "2026-11") -> dict:
    limits = limits or LIMITS
    checks = []
    worst = "pass"
    for ax, b, s in zip("xyz", tdb, tdsf):
        for name, v, lim, unit in (("tdb_mg_per_c", b, limits["tdb_mg_per_c"], "mg/C"), ("tdsf_ppm_per_c", s, limits["tdsf_ppm_per_c"], "ppm/C")):
            outcome = "pass" if abs(v) <= lim else "fail"
            if outcome == "fail":
                worst = "fail"
            checks.append({"measurement": name, "axis": ax, "value": v, "sigma": 0.01, "unit": unit, "low": -lim,
                           "high": lim, "outcome": outcome, "reason": ""})
    fails = [c for c in checks if c["outcome"] == "fail"]
    return {"verdict": worst, "grade": "A" if worst == "pass" else "reject", "tray": "T-A" if worst == "pass" else "T-reject",
            "reason": "; ".join(f"{c['axis']} {c['measurement']} {c['value']:.4g} {c['unit']}, limit {c['high']:g}" for c in fails),
            "attempt": attempt, "limits_name": limits_name, "limits_version": limits_version, "checks": checks}


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
            w.submit(DutResult(batch, slot, serial, thermal=ThermalReport.from_json(thermal_result(tdb, tdsf))))
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


@dataclass
class Lot:
    """One batch of judged runs for the SPC/Pareto tests: a product (trace), the limits set it was
    judged by, and the TDB x values in order (the other axes and TDSF are quiet). `error_slots`:
    extra runs that end in error, each (state, reason): state 'faulted' (no checks) or 'done'
    (TDB y not measured)."""

    trace: Trace
    tdb_x: list[float]
    limits_version: str = "1"
    limits_name: str = "LIS3DSH"
    tdb_limit: float = 1.5
    judged_day: str = "2026-11-20"  # every run of the lot judged that day (UTC), a minute apart
    error_slots: list[tuple[str, str]] = field(default_factory=list)


def write_lots(db: Database, lots: list[Lot], serial_prefix: str = "P", seed: int = 7) -> list[dict]:
    """Each lot as one finished batch (db.create_batch(..., trace=...)), through the real DbWriter;
    then each run's judged_at set to its lot's day (the writer stamps 'now'). Returns per run:
    batch, run, serial, slot, tdb (x, y, z), verdict, lot index, judged_at (datetime)."""
    rng = random.Random(seed)
    written: list[dict] = []
    w = DbWriter(db, interval_s=0.02)
    limits = dict(LIMITS)
    for k, lot in enumerate(lots):
        batch = db.create_batch("fast-thermal", "carla", {"name": db.station}, state="running", trace=lot.trace)
        lim = {**limits, "tdb_mg_per_c": lot.tdb_limit}
        day = datetime.fromisoformat(lot.judged_day).replace(tzinfo=timezone.utc)
        mine = []
        for i, x in enumerate(lot.tdb_x):
            slot, serial = f"s{i + 1:02d}", f"{serial_prefix}{k:02d}{i:03d}"
            run = db.create_run(batch, slot, serial, "LIS3DSH", {"serial": serial, "sensor": "LIS3DSH"})
            w.bind_run(batch, slot, run)
            tdb = (x, round(rng.gauss(0.1, 0.05), 4), round(rng.gauss(0.1, 0.05), 4))
            tdsf = tuple(round(rng.gauss(-120.0, 20.0), 1) for _ in range(3))
            v = verdict_of(tdb, tdsf, limits=lim, limits_name=lot.limits_name, limits_version=lot.limits_version)
            w.submit(SlotStateChanged(batch, slot, serial, "done"))
            w.submit(DutVerdict(batch, slot, serial, verdict=v))
            mine.append({"batch": batch, "run": run, "serial": serial, "slot": slot, "tdb": tdb,
                         "verdict": v["verdict"], "lot": k})
        for j, (state, reason) in enumerate(lot.error_slots):
            slot, serial = f"e{j + 1:02d}", f"{serial_prefix}{k:02d}E{j:02d}"
            run = db.create_run(batch, slot, serial, "LIS3DSH", {"serial": serial, "sensor": "LIS3DSH"})
            w.bind_run(batch, slot, run)
            if state == "done":  # finished, but TDB y was not measured: an error check, value None
                tdb = (0.1, 0.1, 0.1)
                v = verdict_of(tdb, (-100.0,) * 3, limits=lim, limits_name=lot.limits_name,
                               limits_version=lot.limits_version)
                for c in v["checks"]:
                    if c["measurement"] == "tdb_mg_per_c" and c["axis"] == "y":
                        c.update(value=None, outcome="error", reason="y TDB not measured")
                v.update(verdict="error", reason="y TDB not measured", reasons=["y TDB not measured"])
            else:
                v = {"verdict": "error", "grade": "retest", "tray": "retest", "reason": reason, "reasons": [reason],
                     "attempt": 1, "limits_name": lot.limits_name, "limits_version": lot.limits_version, "checks": []}
            w.submit(SlotStateChanged(batch, slot, serial, state, fault_reason="" if state == "done" else reason))
            w.submit(DutVerdict(batch, slot, serial, verdict=v))
            mine.append({"batch": batch, "run": run, "serial": serial, "slot": slot, "verdict": "error", "lot": k,
                         "tdb": (0.1, None, 0.1) if state == "done" else None})
        w.flush()
        db.set_batch_state(batch, "finished")
        for i, m in enumerate(mine):  # a minute apart, in the order written
            m["judged_at"] = day.replace(hour=8) + timedelta(minutes=i)
            with db.session() as s:
                s.execute(update(DutRun).where(DutRun.id == m["run"]).values(judged_at=m["judged_at"]))
        written += mine
    w.close()
    return written


def spc_line_lots() -> list[Lot]:
    """A line's month in four batches, for the SPC/Pareto tests (REST and browser):

    A  ACC-100 rev A, WO-1, limits LIS3DSH v1 (TDB ±1.5), 2026-11-18: 15 parts near 0.2 mg/C, then
       a shift to 0.6 (rule 2 fires on the 9th after it), then 1.2, 1.6 (above its USL), 1.2; and
       three runs in error: two faulted (no samples; link lost), one with TDB y not measured (its
       TDB x 0.1 is a point).
    B  ACC-100 rev A, WO-2, limits LIS3DSH v2 (TDB ±1.0), 2026-11-19: 12 parts near 0.7, two at 1.1
       (out of ITS spec, inside v1's): n=12, no Cpk.
    C  ACC-200 rev B, WO-3, limits ADXL355 v1 (TDB ±1.5), 2026-11-20: 28 parts spread wide
       (Cpk about 0.7, highlighted).
    D  no product (an old batch), limits LIS3DSH v1, 2026-11-20, 6 parts: write it through a
       second Database of station 'line-9' (write_lots(db9, [lots[3]])).
    """
    rng = random.Random(24)
    a = ([round(0.2 + rng.uniform(-0.05, 0.05), 4) for _ in range(15)]
         + [round(0.6 + rng.uniform(-0.05, 0.05), 4) for _ in range(12)] + [1.2, 1.6, 1.2])
    b = [round(0.7 + rng.uniform(-0.05, 0.05), 4) for _ in range(10)] + [1.1, 1.1]
    c = [round(0.55 + rng.gauss(0.0, 0.45), 4) for _ in range(28)]
    d = [round(0.3 + rng.uniform(-0.05, 0.05), 4) for _ in range(6)]
    return [
        Lot(Trace(work_order="WO-1", part_number="ACC-100", part_revision="A"), a, "1", judged_day="2026-11-18",
            error_slots=[("faulted", "serial /dev/ttyACM30: no samples for 12.0 s"),  # the daemon's own words
                         ("faulted", "serial /dev/ttyACM31: link lost: device reports readiness to read but "
                                     "returned no data"), ("done", "")]),
        Lot(Trace(work_order="WO-2", part_number="ACC-100", part_revision="A"), b, "2", tdb_limit=1.0,
            judged_day="2026-11-19"),
        Lot(Trace(work_order="WO-3", part_number="ACC-200", part_revision="B"), c, "1", limits_name="ADXL355",
            judged_day="2026-11-20"),
        Lot(Trace(), d, "1", judged_day="2026-11-20"),
    ]


def write_spc_line(db: Database, db_other_station: Database) -> list[dict]:
    """spc_line_lots() into the database: A, B, C by `db`, D by `db_other_station` (same file)."""
    lots = spc_line_lots()
    return write_lots(db, lots[:3]) + [dict(w, lot=3) for w in write_lots(db_other_station, lots[3:], serial_prefix="Q")]


__all__ = ["write_batches", "write_unjudged", "write_lots", "Lot", "spc_line_lots", "write_spc_line", "segments_for", "verdict_of", "thermal_result",
           "DutVerdict"]
