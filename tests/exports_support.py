"""Readers and checks for tests/test_exports.py: what the database says about a batch (its rows,
read straight from the tables), the STDF read back with Semi-ATE-STDF, the OCPTV lines validated
against the spec's schema, and the comparison of each with the database. The numbers a yield tool
is promised (hard bins, OCPTV diagnosis types) are written here from docs/exports.md, not imported
from the code under test. `rewrite` and `mutate` change one field of an export for the mutation
tests."""

from __future__ import annotations

import io
import json
import struct
from collections import Counter
from datetime import datetime
from pathlib import Path

from jsonschema import Draft202012Validator
from referencing import Registry, Resource
from Semi_ATE import STDF
from sqlalchemy import select

from db import Database
from db.models import Batch, Dut, DutRun

SCHEMA = Path(__file__).parent / "data" / "ocptv_output_schema.json"
HARD_BIN = {"pass": 1, "marginal": 2, "fail": 3, "error": 4}
DIAGNOSIS = {"pass": "PASS", "marginal": "UNKNOWN", "fail": "FAIL", "error": "FAIL"}


def load_validator() -> Draft202012Validator:
    """The bundled OCPTV schema: every spec file a resource under its own $id, root.json the entry."""
    bundle = json.loads(SCHEMA.read_text())
    Draft202012Validator.check_schema(bundle)
    registry = Registry().with_resources((d["$id"], Resource.from_contents(d)) for d in bundle["$defs"].values())
    return Draft202012Validator(bundle, registry=registry)


def db_truth(db: Database, batch_id: int) -> tuple[dict, dict]:
    """(batch row fields, {serial: run row fields}) read straight from the tables."""
    with db.session() as s:
        b = s.get(Batch, batch_id)
        batch = {k: getattr(b, k) for k in ("operator", "profile", "station", "created_at", "work_order", "part_number",
                                            "part_revision", "lot")}
        rows = s.execute(select(DutRun, Dut.serial).join(Dut, Dut.id == DutRun.dut_id)
                         .where(DutRun.batch_id == batch_id)).all()
        runs = {serial: {"id": r.id, "slot": r.slot, "state": r.state, "verdict": r.verdict, "grade": r.grade,
                         "label_serial": r.label_serial or "", "started_at": r.started_at,
                         "checks": list((r.verdict_detail or {}).get("checks") or [])}
                for r, serial in rows}
    return batch, runs


def f32(v: float) -> float:
    return struct.unpack("<f", struct.pack("<f", v))[0]


def bits(flags: list[str]) -> int:
    """Semi-ATE-STDF gives a B*1 as 8 characters, bit 7 first."""
    return int("".join(flags), 2)


def read_stdf(data: bytes) -> dict:
    """Every record Semi-ATE-STDF reads, grouped: header, per-part (PIR .. PRR on a site), summaries."""
    out: dict = {"order": [], "parts": [], "dtr": [], "hbr": [], "sbr": []}
    open_parts: dict[int, dict] = {}
    for rec in STDF.records_from_file(io.BytesIO(data)):
        d = rec.to_dict()
        out["order"].append(rec.id)
        if rec.id in ("MIR", "MRR", "PCR", "FAR"):
            out[rec.id.lower()] = d
        elif rec.id == "PIR":
            open_parts[d["SITE_NUM"]] = {"site": d["SITE_NUM"], "ptr": [], "dtr": []}
        elif rec.id == "PTR":
            open_parts[d["SITE_NUM"]]["ptr"].append(d)
        elif rec.id == "DTR":
            (next(iter(open_parts.values()))["dtr"] if open_parts else out["dtr"]).append(d["TEXT_DAT"])
        elif rec.id == "PRR":
            part = open_parts.pop(d["SITE_NUM"])
            part["prr"] = d
            out["parts"].append(part)
        elif rec.id in ("HBR", "SBR"):
            out[rec.id.lower()].append(d)
    assert not open_parts, "a PIR without its PRR"
    return out


def check_stdf(data: bytes, db: Database, batch_id: int, serials: set[str] | None = None) -> None:
    """The STDF says what the database says, for every DUT (or the serials given)."""
    batch, runs = db_truth(db, batch_id)
    if serials is not None:
        runs = {s: r for s, r in runs.items() if s in serials}
    f = read_stdf(data)
    assert f["order"][:2] == ["FAR", "MIR"] and f["order"][-1] == "MRR"
    assert (f["far"]["CPU_TYPE"], f["far"]["STDF_VER"]) == (2, 4)
    mir = f["mir"]
    assert (mir["LOT_ID"], mir["PART_TYP"], mir["DSGN_REV"], mir["SBLOT_ID"]) == (
        batch["lot"], batch["part_number"], batch["part_revision"], batch["work_order"])
    assert (mir["OPER_NAM"], mir["NODE_NAM"], mir["JOB_NAM"]) == (batch["operator"], batch["station"], batch["profile"])
    assert mir["SETUP_T"] == int(batch["created_at"].timestamp())
    assert mir["START_T"] == int(min(r["started_at"] for r in runs.values()).timestamp())
    assert f"work_order={batch['work_order']}" in f["dtr"] and f"lot={batch['lot']}" in f["dtr"]
    parts = {p["prr"]["PART_ID"]: p for p in f["parts"]}
    assert set(parts) == set(runs), "every DUT has its part record, no other"
    for serial, run in runs.items():
        part, prr = parts[serial], parts[serial]["prr"]
        flags = bits(prr["PART_FLG"])
        assert bool(flags & 0x08) == (run["verdict"] != "pass"), f"{serial}: pass/fail flag"
        assert not flags & 0x10, f"{serial}: the pass/fail flag is valid"
        assert bool(flags & 0x04) == (run["state"] != "done"), f"{serial}: abnormal end"
        assert prr["HARD_BIN"] == HARD_BIN[run["verdict"]], f"{serial}: hard bin"
        assert prr["PART_TXT"].startswith(f"{run['verdict']} grade {run['grade']}")
        assert f"label_serial={run['label_serial']}" in part["dtr"] and f"run_id={run['id']}" in part["dtr"]
        assert prr["NUM_TEST"] == len(run["checks"]) == len(part["ptr"])
        ptrs = {p["TEST_TXT"]: p for p in part["ptr"]}
        assert len({p["TEST_NUM"] for p in part["ptr"]}) == len(part["ptr"]), "test numbers unique per part"
        for c in run["checks"]:
            p = ptrs[f"{c['measurement']} {c['axis']}" if c["axis"] else c["measurement"]]
            test_flg, opt = bits(p["TEST_FLG"]), bits(p["OPT_FLAG"])
            what = f"{serial} {p['TEST_TXT']}"
            if c["value"] is None:
                assert test_flg & 0x12 == 0x12 and test_flg & 0x80, f"{what}: not executed, invalid, failed"
            else:
                assert p["RESULT"] == f32(c["value"]), what
                assert bool(test_flg & 0x80) == (c["outcome"] != "pass"), f"{what}: test failed flag"
            assert p["UNITS"] == c["unit"], what
            if c["low"] is None:
                assert opt & 0x40, f"{what}: no low limit"
            else:
                assert not opt & 0x40 and p["LO_LIMIT"] == f32(c["low"]), f"{what}: low limit"
            if c["high"] is None:
                assert opt & 0x80, f"{what}: no high limit"
            else:
                assert not opt & 0x80 and p["HI_LIMIT"] == f32(c["high"]), f"{what}: high limit"
    want = Counter(HARD_BIN[r["verdict"]] for r in runs.values())
    assert {h["HBIN_NUM"]: h["HBIN_CNT"] for h in f["hbr"]} == want
    assert {h["HBIN_NUM"]: h["HBIN_PF"] for h in f["hbr"]} == {n: "P" if n == 1 else "F" for n in want}
    assert sum(s["SBIN_CNT"] for s in f["sbr"]) == len(runs)
    assert f["pcr"]["PART_CNT"] == len(runs) and f["pcr"]["GOOD_CNT"] == sum(r["verdict"] == "pass" for r in runs.values())


def rewrite(data: bytes, kind: str, pick, field: str, value) -> bytes:
    """The STDF with one field of the first `kind` record that `pick` accepts changed (re-packed by
    Semi-ATE-STDF: a file a tool could be given)."""
    out, done = [], False
    for rec in STDF.records_from_file(io.BytesIO(data)):
        if not done and rec.id == kind and pick(rec.to_dict()):
            rec.set_value(field, value)
            done = True
        out.append(rec.__repr__())
    assert done, f"no {kind} to change"
    return b"".join(out)


def read_ocptv(data: bytes, validator) -> list[dict]:
    """Every line validated against the spec's schema; the outputs split at each schemaVersion."""
    runs: list[dict] = []
    for n, line in enumerate(data.decode().splitlines()):
        obj = json.loads(line)
        errors = [e.message for e in validator.iter_errors(obj)]
        assert not errors, f"line {n + 1} breaks the OCPTV schema: {errors[:3]}"
        datetime.fromisoformat(obj["timestamp"].replace("Z", "+00:00"))
        if "schemaVersion" in obj:
            runs.append({"seq": [], "measurements": [], "errors": [], "first": obj})
        run = runs[-1]
        run["seq"].append(obj["sequenceNumber"])
        art = obj.get("testRunArtifact") or obj.get("testStepArtifact") or {}
        for key in ("testRunStart", "testRunEnd", "diagnosis", "testStepEnd"):
            if key in art:
                run[key] = art[key]
        if "testRunStart" in art:
            run["start_time"] = obj["timestamp"]
        run["measurements"] += [art["measurement"]] if "measurement" in art else []
        run["errors"] += [art["error"]] if "error" in art else []
    return runs


def check_ocptv(data: bytes, validator, db: Database, batch_id: int) -> None:
    batch, runs = db_truth(db, batch_id)
    outputs = {o["testRunStart"]["dutInfo"]["name"]: o for o in read_ocptv(data, validator)}
    assert set(outputs) == set(runs), "one testRun per DUT run"
    for serial, run in runs.items():
        o = outputs[serial]
        assert o["seq"] == list(range(len(o["seq"]))), f"{serial}: sequence numbers"
        dut = o["testRunStart"]["dutInfo"]
        hw = dut["hardwareInfos"][0]
        assert (hw["serialNumber"], hw["partNumber"], hw["revision"], hw["location"]) == (
            serial, batch["part_number"], batch["part_revision"], run["slot"])
        assert dut["metadata"].get("label_serial", "") == run["label_serial"], f"{serial}: label serial"
        params = o["testRunStart"]["parameters"]
        assert (params["work_order"], params["lot"], params["run_id"]) == (batch["work_order"], batch["lot"], run["id"])
        assert datetime.fromisoformat(o["start_time"].replace("Z", "+00:00")) == run["started_at"]
        assert o["diagnosis"]["verdict"] == run["verdict"], serial
        assert o["diagnosis"]["type"] == DIAGNOSIS[run["verdict"]], serial
        end = o["testRunEnd"]
        if run["state"] == "done":
            assert end == {"status": "COMPLETE", "result": "PASS" if run["verdict"] == "pass" else "FAIL"}, serial
        else:
            assert end == {"status": "ERROR", "result": "NOT_APPLICABLE"}, serial
            assert any(e["symptom"] == f"run-{run['state']}" for e in o["errors"])
        got = {(m["name"], (m.get("subcomponent") or {}).get("name")): m for m in o["measurements"]}
        measured = [c for c in run["checks"] if c["value"] is not None]
        assert len(got) == len(o["measurements"]) == len(measured), serial
        assert sum(e["symptom"] == "not-measured" for e in o["errors"]) == len(run["checks"]) - len(measured)
        for c in measured:
            m = got[(c["measurement"], c["axis"])]
            assert (m["value"], m["unit"], m["metadata"]["outcome"]) == (c["value"], c["unit"], c["outcome"]), serial
            limits = {v["type"]: v["value"] for v in m["validators"]}
            want = {k: v for k, v in (("GREATER_THAN_OR_EQUAL", c["low"]), ("LESS_THAN_OR_EQUAL", c["high"]))
                    if v is not None}
            assert limits == want, f"{serial} {c['measurement']} {c['axis']}: limits"


def mutate(data: bytes, serial: str, change) -> bytes:
    """Change one artifact of the serial's output (change returns True once it changed something)."""
    lines, current, done = [], None, False
    for line in data.decode().splitlines():
        obj = json.loads(line)
        start = (obj.get("testRunArtifact") or {}).get("testRunStart")
        current = start["dutInfo"]["name"] if start else current
        if current == serial and not done:
            done = bool(change(obj))
        lines.append(json.dumps(obj))
    assert done
    return ("\n".join(lines) + "\n").encode()


def set_at(path: list[str], value, where=lambda obj: True):
    def change(obj):
        node = obj
        for key in path[:-1]:
            node = node.get(key) if isinstance(node, dict) else None
            if node is None:
                return False
        if not where(obj) or path[-1] not in node:
            return False
        node[path[-1]] = value
        return True
    return change


