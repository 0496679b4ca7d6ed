"""STDF V4 of an export report (docs/exports.md has the record-by-record map).

Written with Semi-ATE-STDF (`Semi_ATE.STDF`), the maintained Python STDF library, so the bytes
are packed by the same code that reads them back in the tests. Little-endian (FAR CPU_TYPE 2).

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
    PCR, HBR, SBR             summaries over all sites (HEAD_NUM 255)
    MRR                       last part judged (FINISH_T), batch state and reason

Times are U*4 seconds since 1970 UTC (the station's clock is UTC; STDF leaves the zone open).
Numbers are R*4 (IEEE single precision): a value reads back as float32(value), ~7 digits.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any

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


def _stdf():
    from Semi_ATE import STDF

    return STDF


def _record(kind: str, **fields: Any):
    """One record object with its fields set (Semi-ATE-STDF validates each value against its type)."""
    rec = getattr(_stdf(), kind)(endian=ENDIAN)
    for name, value in fields.items():
        if value is not None:
            rec.set_value(name, value)
    return rec


def _bytes(rec) -> bytes:
    """The packed record: Semi-ATE-STDF's records return their bytes from __repr__ (its README's
    documented way to write; repr() itself would refuse a bytes result)."""
    return rec.__repr__()


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
    return b"".join(_bytes(r) for r in recs)


__all__ = ["write_stdf", "ptr_fields", "prr_fields", "mir_fields", "stdf_time", "part_text"]
