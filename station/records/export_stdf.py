"""STDF V4 of an export report (docs/exports.md has the record-by-record map).

Written with stdfast (PyPI `stdfast`, 0.2.x, 2026: typed pydantic models per record, packed by its
Rust core; docs/exports.md says why it replaced Semi-ATE-STDF, last released 2022-06). The tests
read the bytes back with other libraries (Semi-ATE-STDF, pystdf), never with the writer's own
code. Little-endian (FAR CPU_TYPE 2). Text fields are ASCII of at most 255 characters (STDF C*n):
`stdf_text` makes them so before the library sees them (stdfast would write UTF-8, which STDF
readers refuse, and panics on a longer string).

Mapping, in file order:
    FAR                       CPU type 2, STDF version 4
    MIR                       lot (LOT_ID), part number (PART_TYP), part revision (DSGN_REV), work
                              order (SBLOT_ID: the station has no sublots), station (NODE_NAM),
                              operator (OPER_NAM), profile (JOB_NAM), software version (JOB_REV,
                              EXEC_VER), limits name/version (SPEC_NAM/SPEC_VER), batch created
                              (SETUP_T) and first part started (START_T)
    SDR                       one per slot: site group = site = the slot's number, slot name in EXTR_ID
    DTR                       the batch's traceability fields as `key=value` text
    per part  PIR, DTR (label_serial=, run_id=, attempt=), PTR per check, PRR
    TSR                       one per test number per site (HEAD_NUM 1, SITE_NUM = the slot's site),
                              then one per test number over all sites (HEAD_NUM 255): executions,
                              failures, min/max, sum and sum of squares of the results
    PCR, HBR, SBR             summaries over all sites (HEAD_NUM 255)
    MRR                       last part judged (FINISH_T), batch state and reason

Times are U*4 seconds since 1970 UTC (the station's clock is UTC; STDF leaves the zone open).
Numbers are R*4 (IEEE single precision): a value reads back as float32(value), ~7 digits.
"""

from __future__ import annotations

import math
import os
import tempfile
import unicodedata
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from pydantic import BaseModel

from station.records.export_model import ExportPart, ExportReport, ExportTest

ENDIAN = "<"
SUMMARY_HEAD = 255  # HEAD_NUM of a summary over all sites (HBR, SBR, PCR)
FLOAT32_MAX = 3.4028234663852886e38

# PTR TEST_FLG bits (STDF V4 p. 47)
TEST_RESULT_INVALID = 1 << 1
TEST_NOT_EXECUTED = 1 << 4
TEST_FAILED = 1 << 7
# PTR PARM_FLG bits: above high / below low limit; the limits themselves pass (value == limit is in)
PARM_ABOVE_HIGH = 1 << 3
PARM_BELOW_LOW = 1 << 4
PARM_LIMITS_INCLUSIVE = (1 << 6) | (1 << 7)
# PTR OPT_FLAG bits: bit 1 is reserved and set; no spec limits (bits 2, 3); no low / high test limit (6, 7)
OPT_BASE = (1 << 1) | (1 << 2) | (1 << 3)
OPT_NO_LOW = 1 << 6
OPT_NO_HIGH = 1 << 7
# PRR PART_FLG bits
PART_ABNORMAL_END = 1 << 2
PART_FAILED = 1 << 3
# TSR OPT_FLAG bits (STDF V4 p. 38): set = the field is invalid; bits 3, 6 and 7 are reserved and
# must be 1. The station does not time its checks (TEST_TIM is always invalid).
TSR_NO_MIN = 1 << 0
TSR_NO_MAX = 1 << 1
TSR_NO_TIM = 1 << 2
TSR_NO_SUMS = 1 << 4
TSR_NO_SQRS = 1 << 5
TSR_RESERVED = (1 << 3) | (1 << 6) | (1 << 7)
TEXT_MAX = 255  # STDF C*n: a one-byte length
# what NFKD cannot take to ASCII, in the station's own words
_ASCII_WORDS = {"°": "deg", "µ": "u", "μ": "u", "√": "sqrt", "±": "+/-", "×": "x", "–": "-", "—": "-",
                "‘": "'", "’": "'", "“": '"', "”": '"', "…": "...", "ß": "ss"}
# stdfast's field names are the spec's in lower case, but for these (stdfast 0.2.1)
_FIELD_NAMES = {("SDR", "EXTR_ID"): "extr_i"}


def stdf_text(text: str, limit: int = TEXT_MAX) -> str:
    """`text` as an STDF C*n holds it: ASCII (accents dropped, µ/° spelled out, anything else '?'),
    at most `limit` characters. STDF readers decode C*n as ASCII: one UTF-8 byte makes the whole
    file unreadable to them."""
    out = []
    for ch in unicodedata.normalize("NFKD", "".join(_ASCII_WORDS.get(c, c) for c in text)):
        if ord(ch) < 128:
            out.append(ch if ch.isprintable() or ch in "\t" else " ")
        elif not unicodedata.combining(ch):
            out.append("?")
    return "".join(out)[:limit]


def _record(kind: str, **fields: Any) -> BaseModel:
    """One stdfast record model with its fields set, by the spec's field names. stdfast validates
    each value against its STDF type (U*1 0..255 ...); a name it does not have is an error here,
    not a field silently left at its default."""
    from stdfast import records

    model: type[BaseModel] = getattr(records, kind)
    values: dict[str, Any] = {}
    for name, value in fields.items():
        key = _FIELD_NAMES.get((kind, name), name.lower())
        if key not in model.model_fields:
            raise KeyError(f"STDF {kind} has no field {name} (stdfast {kind}: {', '.join(model.model_fields)})")
        if value is None:
            continue
        if isinstance(value, str):
            value = stdf_text(value, 1 if model.model_fields[key].annotation is not str else TEXT_MAX)
        values[key] = value
    return model(**values)


def _pack(recs: list[BaseModel]) -> bytes:
    """The records as STDF bytes. stdfast writes to a named file only: a private temporary file,
    read back and removed."""
    import stdfast

    fd, path = tempfile.mkstemp(prefix="station-", suffix=".stdf")
    os.close(fd)
    try:
        try:
            stdfast.write_stdf(path, recs)  # type: ignore[no-untyped-call]  # its stub leaves the arguments untyped
        except (KeyboardInterrupt, SystemExit):
            raise
        except BaseException as exc:  # a panic of its Rust core is pyo3's PanicException, no Exception:
            # uncaught, it would pass every `except Exception` of the web and the CLI
            raise ValueError(f"STDF not written: stdfast failed: {type(exc).__name__}: {exc}") from exc
        with open(path, "rb") as f:
            return f.read()
    finally:
        os.unlink(path)


def stdf_time(t: datetime | None) -> int:
    return 0 if t is None else max(0, int(t.timestamp()))


def _r4(value: float) -> float:
    """A value R*4 can hold (a larger one is clipped to the float32 range, keeping its sign)."""
    return max(-FLOAT32_MAX, min(FLOAT32_MAX, value))


def ptr_fields(test: ExportTest, site: int) -> dict[str, Any]:
    """The PTR of one check: result, limits, units and the pass/fail flags of the check's outcome.
    marginal counts as failed (the station did not accept it); a check with no value is flagged
    not executed, result invalid, failed."""
    test_flg = 0
    result = 0.0
    parm_flg = PARM_LIMITS_INCLUSIVE
    if test.value is None:
        test_flg = TEST_RESULT_INVALID | TEST_NOT_EXECUTED | TEST_FAILED
    else:
        result = _r4(test.value)
        if test.outcome != "pass":
            test_flg |= TEST_FAILED
        if test.high is not None and test.value > test.high:
            parm_flg |= PARM_ABOVE_HIGH
        if test.low is not None and test.value < test.low:
            parm_flg |= PARM_BELOW_LOW
    opt = OPT_BASE | (OPT_NO_LOW if test.low is None else 0) | (OPT_NO_HIGH if test.high is None else 0)
    return {"TEST_NUM": test.test_number, "HEAD_NUM": 1, "SITE_NUM": site, "TEST_FLG": test_flg, "PARM_FLG": parm_flg,
            "RESULT": result, "TEST_TXT": test.label, "ALARM_ID": "", "OPT_FLAG": opt, "RES_SCAL": 0, "LLM_SCAL": 0,
            "HLM_SCAL": 0, "LO_LIMIT": _r4(test.low) if test.low is not None else 0.0,
            "HI_LIMIT": _r4(test.high) if test.high is not None else 0.0, "UNITS": test.unit}


def part_text(part: ExportPart) -> str:
    """PRR PART_TXT: verdict, grade, tray and the reason (at most 255 characters in STDF)."""
    text = f"{part.verdict} grade {part.grade or '-'} tray {part.tray or '-'}"
    return f"{text}: {part.reason}" if part.reason else text


def prr_fields(part: ExportPart) -> dict[str, Any]:
    flags = 0 if part.passed else PART_FAILED
    if not part.completed:
        flags |= PART_ABNORMAL_END
    test_ms = 0
    if part.started_at is not None and part.ended_at is not None:
        test_ms = min(0xFFFFFFFF, max(0, int((part.ended_at - part.started_at).total_seconds() * 1000)))
    return {"HEAD_NUM": 1, "SITE_NUM": part.site, "PART_FLG": flags, "NUM_TEST": len(part.tests),
            "HARD_BIN": part.hard_bin, "SOFT_BIN": part.soft_bin, "TEST_T": test_ms, "PART_ID": part.serial,
            "PART_TXT": part_text(part)}


def _one(values: set[str]) -> str:
    """A batch-level field the runs share (limits name/version); several: joined, sorted."""
    return ",".join(sorted(v for v in values if v))


def mir_fields(report: ExportReport) -> dict[str, Any]:
    return {
        "SETUP_T": stdf_time(report.created_at), "START_T": stdf_time(report.started_at), "STAT_NUM": 1,
        "MODE_COD": "D" if report.replay_of else "P",  # a replay is a development run, not production
        "LOT_ID": report.lot, "PART_TYP": report.part_number, "DSGN_REV": report.part_revision,
        "SBLOT_ID": report.work_order, "NODE_NAM": report.station, "OPER_NAM": report.operator,
        "TSTR_TYP": "thermal-cal-station", "JOB_NAM": report.profile, "JOB_REV": report.software_version,
        "EXEC_TYP": "thermal-cal-station", "EXEC_VER": report.software_version, "TEST_COD": "CAL",
        "SPEC_NAM": _one({p.limits_name for p in report.parts}),
        "SPEC_VER": _one({p.limits_version for p in report.parts}),
        "USER_TXT": f"batch {report.batch_id}" + (f" run {report.parts[0].run_id}" if report.scope == "run" else ""),
    }


def batch_dtr_texts(report: ExportReport) -> list[str]:
    out = [f"batch_id={report.batch_id}", f"work_order={report.work_order}", f"part_number={report.part_number}",
           f"part_revision={report.part_revision}", f"lot={report.lot}"]
    if report.replay_of:
        out.append(f"replay_of={report.replay_of}")
    return out


@dataclass
class TestSynopsis:
    """One TSR: a test number's executions on one site (or all: head 255) and their results."""

    test: ExportTest  # the first execution: name, label, unit
    executed: int = 0
    failed: int = 0
    lo: float = math.inf
    hi: float = -math.inf
    total: float = 0.0
    squares: float = 0.0

    def add(self, test: ExportTest) -> None:
        """One PTR of this test: a check without a value was not executed (its PTR says so)."""
        if test.value is None:
            return
        self.executed += 1
        if test.outcome != "pass":
            self.failed += 1
        v = float(test.value)
        self.lo, self.hi = min(self.lo, v), max(self.hi, v)
        self.total += v
        self.squares += v * v


def test_synopses(report: ExportReport) -> tuple[dict[tuple[int, int], TestSynopsis], dict[int, TestSynopsis]]:
    """(per (site, test number), per test number over all sites), in the order tests first appear."""
    per_site: dict[tuple[int, int], TestSynopsis] = {}
    overall: dict[int, TestSynopsis] = {}
    for part in report.parts:
        for t in part.tests:
            per_site.setdefault((part.site, t.test_number), TestSynopsis(t)).add(t)
            overall.setdefault(t.test_number, TestSynopsis(t)).add(t)
    return per_site, overall


def tsr_fields(syn: TestSynopsis, head: int, site: int, sequence: str) -> dict[str, Any]:
    """The TSR of a synopsis. Min, max, sum and sum of squares are valid (their OPT_FLAG bits clear)
    when the test was executed at least once; TEST_TIM never is (the station does not time its
    checks). ALRM_CNT is 0: the station raises no tester alarm on a check (STDF's alarm is the
    tester's, not a marginal result)."""
    t = syn.test
    opt = TSR_RESERVED | TSR_NO_TIM
    if syn.executed == 0:
        opt |= TSR_NO_MIN | TSR_NO_MAX | TSR_NO_SUMS | TSR_NO_SQRS
    label = f"{t.label} ({t.unit})" if t.unit else t.label
    done = syn.executed > 0
    return {"HEAD_NUM": head, "SITE_NUM": site, "TEST_TYP": "P", "TEST_NUM": t.test_number,
            "EXEC_CNT": syn.executed, "FAIL_CNT": syn.failed, "ALRM_CNT": 0, "TEST_NAM": t.label,
            "SEQ_NAME": sequence, "TEST_LBL": label, "OPT_FLAG": opt, "TEST_TIM": 0.0,
            "TEST_MIN": _r4(syn.lo) if done else 0.0, "TEST_MAX": _r4(syn.hi) if done else 0.0,
            "TST_SUMS": _r4(syn.total) if done else 0.0, "TST_SQRS": _r4(syn.squares) if done else 0.0}


def tsr_records(report: ExportReport) -> Iterable[dict[str, Any]]:
    """Every TSR's fields: per site in site order, then the summary over all sites (head 255)."""
    per_site, overall = test_synopses(report)
    for (site, _num), syn in sorted(per_site.items(), key=lambda kv: kv[0]):
        yield tsr_fields(syn, 1, site, report.profile)
    for _num, syn in sorted(overall.items()):
        yield tsr_fields(syn, SUMMARY_HEAD, 0, report.profile)


def write_stdf(report: ExportReport) -> bytes:
    """The whole STDF V4 file of the report."""
    recs = [_record("FAR", CPU_TYPE=2, STDF_VER=4), _record("MIR", **mir_fields(report))]
    for slot, site in sorted({(p.slot, p.site) for p in report.parts}, key=lambda s: s[1]):
        recs.append(_record("SDR", HEAD_NUM=1, SITE_GRP=site, SITE_CNT=1, SITE_NUM=[site], EXTR_TYP="slot",
                            EXTR_ID=slot))
    recs += [_record("DTR", TEXT_DAT=t) for t in batch_dtr_texts(report)]
    for part in report.parts:
        recs.append(_record("PIR", HEAD_NUM=1, SITE_NUM=part.site))
        for text in (f"label_serial={part.label_serial}", f"run_id={part.run_id}", f"attempt={part.attempt}"):
            recs.append(_record("DTR", TEXT_DAT=text))
        recs += [_record("PTR", **ptr_fields(t, part.site)) for t in part.tests]
        recs.append(_record("PRR", **prr_fields(part)))
    recs += [_record("TSR", **f) for f in tsr_records(report)]  # after the last PRR (STDF V4: real-time data)
    parts = report.parts
    recs.append(_record("PCR", HEAD_NUM=SUMMARY_HEAD, SITE_NUM=0, PART_CNT=len(parts),
                        RTST_CNT=sum(1 for p in parts if p.attempt > 1),
                        ABRT_CNT=sum(1 for p in parts if not p.completed),
                        GOOD_CNT=sum(1 for p in parts if p.passed)))
    for b in report.hard_bins():
        recs.append(_record("HBR", HEAD_NUM=SUMMARY_HEAD, SITE_NUM=0, HBIN_NUM=b.number, HBIN_CNT=b.count,
                            HBIN_PF="P" if b.passed else "F", HBIN_NAM=b.name))
    for b in report.soft_bins():
        recs.append(_record("SBR", HEAD_NUM=SUMMARY_HEAD, SITE_NUM=0, SBIN_NUM=b.number, SBIN_CNT=b.count,
                            SBIN_PF="P" if b.passed else "F", SBIN_NAM=b.name))
    recs.append(_record("MRR", FINISH_T=stdf_time(report.finished_at), USR_DESC=f"batch {report.batch_state}",
                        EXC_DESC=report.batch_reason))
    return _pack(recs)


__all__ = ["write_stdf", "ptr_fields", "prr_fields", "mir_fields", "tsr_fields", "tsr_records", "test_synopses",
           "stdf_text", "stdf_time", "part_text", "TestSynopsis"]
