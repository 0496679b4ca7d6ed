"""The STDF's Test Synopsis Records (TSR, docs/exports.md), read by an independent reader.

The batch of tests/test_exports.py (every kind of verdict, stored through the real DbWriter) is
exported through the CLI as STDF (written with stdfast) and read back with pystdf, a reader that
shares no code with the writer (nor with Semi-ATE-STDF, the other reader of the export tests).
Every TSR must agree with the PTRs of the same file (executions, failures, min, max, sums) and
with the checks the database holds; the OPT_FLAG bits say which optional fields are valid.
"""

from __future__ import annotations

import io
import math
from collections import defaultdict

import numpy as np
import pytest

from exports_support import db_truth
from test_exports import cli, store  # noqa: F401  (the stored batch: a module fixture)

TEST_NOT_EXECUTED = 1 << 4
TEST_FAILED = 1 << 7
OPT_RESERVED = (1 << 3) | (1 << 6) | (1 << 7)  # STDF V4 TSR OPT_FLAG: reserved, must be 1
OPT_NO_MIN, OPT_NO_MAX, OPT_NO_TIM, OPT_NO_SUMS, OPT_NO_SQRS = 1 << 0, 1 << 1, 1 << 2, 1 << 4, 1 << 5


class Records:
    """A pystdf sink: every record as (name, {field: value}), in file order."""

    def __init__(self) -> None:
        self.records: list[tuple[str, dict]] = []

    def after_send(self, source, data) -> None:
        rectype, fields = data
        self.records.append((type(rectype).__name__.upper(), dict(zip(rectype.fieldNames, fields))))


def read_pystdf(data: bytes) -> list[tuple[str, dict]]:
    from pystdf.IO import Parser

    parser = Parser(inp=io.BytesIO(data))
    sink = Records()
    parser.addSink(sink)
    parser.parse()
    return sink.records


def flag(value) -> int:
    """pystdf gives a B*1 as a list of one byte value (or an int, by version)."""
    if isinstance(value, (list, tuple)):
        return int(value[0]) if value else 0
    if isinstance(value, (bytes, bytearray)):
        return value[0]
    return int(value)


def f32(x: float) -> float:
    return float(np.float32(x))


@pytest.fixture(scope="module")
def stdf(store, tmp_path_factory):  # noqa: F811
    out = tmp_path_factory.mktemp("tsr") / "batch.stdf"
    assert cli("stdf", "--batch", str(store.batch), "--db", str(store.path), "--out", str(out)) == 0
    return read_pystdf(out.read_bytes())


def ptr_truth(records, head_site=None):
    """Per (site, test number) [or per test number: head_site=None is every site] the PTRs' figures."""
    per: dict = defaultdict(lambda: {"exec": 0, "fail": 0, "values": [], "txt": None})
    for name, r in records:
        if name != "PTR":
            continue
        key = (r["SITE_NUM"], r["TEST_NUM"]) if head_site else r["TEST_NUM"]
        f = flag(r["TEST_FLG"])
        per[key]["txt"] = r["TEST_TXT"]
        if f & TEST_NOT_EXECUTED:
            continue
        per[key]["exec"] += 1
        per[key]["fail"] += 1 if f & TEST_FAILED else 0
        per[key]["values"].append(r["RESULT"])
    return per


def test_every_test_has_its_tsrs_per_site_and_over_all_sites(stdf):
    names = [n for n, _ in stdf]
    tsrs = [r for n, r in stdf if n == "TSR"]
    assert tsrs, "no TSR in the file"
    # after the last part, before the summaries and the MRR
    first_tsr, last_prr = names.index("TSR"), len(names) - 1 - names[::-1].index("PRR")
    assert first_tsr > last_prr and names.index("PCR") > first_tsr and names[-1] == "MRR"
    site_tsrs = {(r["SITE_NUM"], r["TEST_NUM"]): r for r in tsrs if r["HEAD_NUM"] == 1}
    summary = {r["TEST_NUM"]: r for r in tsrs if r["HEAD_NUM"] == 255}
    assert len(site_tsrs) + len(summary) == len(tsrs), "a TSR on neither head 1 nor the summary head 255"
    per_site, overall = ptr_truth(stdf, head_site=True), ptr_truth(stdf)
    assert set(site_tsrs) == set(per_site), "one TSR per test number per site that has its PTRs"
    assert set(summary) == set(overall), "one summary TSR per test number"
    for tsr, truth in [*((site_tsrs[k], per_site[k]) for k in per_site), *((summary[k], overall[k]) for k in overall)]:
        where = (tsr["HEAD_NUM"], tsr["SITE_NUM"], tsr["TEST_NUM"])
        assert tsr["TEST_TYP"] == "P", where
        assert (tsr["EXEC_CNT"], tsr["FAIL_CNT"], tsr["ALRM_CNT"]) == (truth["exec"], truth["fail"], 0), where
        assert tsr["TEST_NAM"] == truth["txt"] and tsr["TEST_LBL"].startswith(truth["txt"]), where
        opt = flag(tsr["OPT_FLAG"])
        assert opt & OPT_RESERVED == OPT_RESERVED and opt & OPT_NO_TIM, (where, bin(opt))
        values = truth["values"]
        if not values:
            assert opt & (OPT_NO_MIN | OPT_NO_MAX | OPT_NO_SUMS | OPT_NO_SQRS) == 0b110011, (where, bin(opt))
            continue
        assert opt & (OPT_NO_MIN | OPT_NO_MAX | OPT_NO_SUMS | OPT_NO_SQRS) == 0, (where, bin(opt))
        assert tsr["TEST_MIN"] == min(values) and tsr["TEST_MAX"] == max(values), where
        assert math.isclose(tsr["TST_SUMS"], f32(sum(values)), rel_tol=1e-5, abs_tol=1e-5), where
        assert math.isclose(tsr["TST_SQRS"], f32(sum(v * v for v in values)), rel_tol=1e-5, abs_tol=1e-5), where


def test_tsr_counts_are_the_databases(stdf, store):  # noqa: F811
    """The summary TSRs count what the database's stored checks say: per measurement and axis, how
    many runs have a value (executed) and how many of those did not pass (failed)."""
    _, runs = db_truth(store.db, store.batch)
    want: dict = defaultdict(lambda: [0, 0])
    for run in runs.values():
        for c in run["checks"]:
            label = f"{c['measurement']} {c['axis']}" if c.get("axis") else c["measurement"]
            if c.get("value") is None:
                want[label]  # noqa: B018 - a test that was never executed still has its TSR
                continue
            want[label][0] += 1
            want[label][1] += 1 if c["outcome"] != "pass" else 0
    got = {r["TEST_NAM"]: [r["EXEC_CNT"], r["FAIL_CNT"]] for n, r in stdf if n == "TSR" and r["HEAD_NUM"] == 255}
    assert got == {k: v for k, v in want.items()}
    # this batch: 5 runs with checks (SN-E1 faulted before any); TDB x failed on SN-F1, TDB y was
    # marginal on SN-M1 (a failure to STDF: the station did not accept it)
    assert got["tdb_mg_per_c x"] == [5, 1] and got["tdb_mg_per_c y"] == [5, 1]
    assert got["drift_error_mg z"][0] == 4  # SN-E2's drift z was never measured


def test_text_fields_are_ascii_and_fit():
    """A name an operator typed with accents or units in Unicode is ASCII in the file (readers decode
    C*n as ASCII) and at most 255 characters (the length is one byte)."""
    from station.records.export_stdf import stdf_text

    assert stdf_text("José Müller, 25 °C, 3 µg, √Hz") == "Jose Muller, 25 degC, 3 ug, sqrtHz"
    assert stdf_text("x" * 300) == "x" * 255
    assert stdf_text("中文") == "??"
    assert stdf_text("a\nb") == "a b"


def test_a_library_panic_is_an_ordinary_error():
    """stdfast's Rust core panics (pyo3 PanicException, a BaseException) on a C*n over 255 bytes:
    the writer never hands it one, and if the library panics anyway the caller gets a ValueError
    its `except Exception` catches, not a BaseException that passes through the web and the CLI."""
    from stdfast.records import DTR, FAR

    from station.records.export_stdf import _pack, _record

    assert len(_record("DTR", TEXT_DAT="y" * 400).text_dat) == 255
    with pytest.raises(ValueError, match="stdfast failed"):
        _pack([FAR(cpu_type=2, stdf_ver=4), DTR(text_dat="z" * 300)])
