"""A run stored through DbWriter comes back as exactly the samples that went in (design 5.1 CSV at
the stored precision), `station db export` writes it, and prune keeps segments and results."""

from __future__ import annotations

import subprocess
import sys
from datetime import timedelta

import numpy as np
import pytest
from sqlalchemy import func, select

from db import DbWriter, codec
from db import repository as repo
from db.export import export_run_csv, prune, run_log
from db.models import SampleChunk, SegmentRow, ThermalResultRow, utcnow
from contracts.events import DutResult, SamplesReceived, SegmentLogged, SlotStateChanged
from contracts.run_records import ThermalReport
from contracts.logfile import ACC_DECIMALS, TEMP_DECIMALS, DutLog, format_log, read_log
from contracts.types import SampleBlock, StationError
from db_helpers import THERMAL_JSON, adxl355_stream, lis3dsh_stream, segment, sqlite_db


def _stream_run(db, time_s, acc_g, temp_c, seed=0, seal_samples=1024, slot="s1", serial="SIM0001"):
    """Write a run the way the daemon does: blocks of 10-50 samples, lamp and position per block."""
    batch = db.create_batch("fast-thermal", "tester", {"profile": "fast-thermal"})
    run = db.create_run(batch, slot, serial, "LIS3DSH", {"serial": serial, "ug_per_lsb": 60.0})
    w = DbWriter(db, interval_s=0.05, seal_samples=seal_samples)
    w.bind_run(batch, slot, run)
    rng = np.random.default_rng(seed)
    n = len(time_s)
    i = 0
    lamp = np.zeros(n, np.int8)
    pos = np.zeros(n, np.int64)
    while i < n:
        k = min(n - i, int(rng.integers(10, 51)))
        lamp_on = n // 4 <= i < 3 * n // 4
        position = 0 if i < n // 2 else 1
        lamp[i : i + k] = lamp_on
        pos[i : i + k] = position
        w.submit(SamplesReceived(batch, slot, serial, 0, SampleBlock(time_s[i : i + k], acc_g[i : i + k], temp_c[i : i + k]),
                                 lamp_on=lamp_on, position=position))
        i += k
    w.submit(SegmentLogged(batch, slot, serial, 1, segment(0, 100.0)))
    w.submit(DutResult(batch, slot, serial, thermal=ThermalReport.from_json(THERMAL_JSON)))
    w.submit(SlotStateChanged(batch, slot, serial, "done"))
    w.close()
    return batch, run, lamp, pos


def _data_rows(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if not ln.startswith("#")]


def test_codec_round_trip_is_exact_at_stored_precision():
    for time_s, acc, temp in (lis3dsh_stream(3000), adxl355_stream(3000)):
        q = codec.quantize(time_s, acc, temp, 1, 5)
        back = codec.decode(codec.encode(q)).samples()
        # exactly the doubles the CSV text parses to
        assert np.array_equal(back.acc_g, np.array([[float(f"{v:.{ACC_DECIMALS}f}") for v in row] for row in acc]))
        assert np.array_equal(back.temp_c, np.array([float(f"{v:.{TEMP_DECIMALS}f}") for v in temp]))
        assert np.array_equal(back.lamp, np.ones(len(time_s), np.int8))
        assert np.array_equal(back.position, np.full(len(time_s), 5))


@pytest.mark.parametrize("stream", ["lis3dsh", "adxl355"])
def test_export_gives_back_the_samples_bit_for_bit(tmp_path, stream):
    db = sqlite_db(tmp_path)
    time_s, acc, temp = lis3dsh_stream(5000) if stream == "lis3dsh" else adxl355_stream(5000)
    batch, run, lamp, pos = _stream_run(db, time_s, acc, temp, seal_samples=1024)
    out = run_log(db, run)
    # the numbers: exactly the stored-precision values of what went in
    assert len(out) == len(time_s)
    assert np.array_equal(out.acc_g, np.round(acc, ACC_DECIMALS))
    assert np.array_equal(out.temp_c, np.round(temp, TEMP_DECIMALS))
    assert np.array_equal(out.lamp, lamp) and np.array_equal(out.position, pos)
    # the file: byte-identical rows to the CSV the station would write from the samples directly
    path = export_run_csv(db, run, tmp_path / "run.csv")
    direct = format_log(DutLog(time_s, acc, temp, meta={}, lamp=lamp, position=pos, ref_dir=out.ref_dir))
    assert _data_rows(path.read_text()) == _data_rows(direct)
    back = read_log(path)
    assert back.serial == "SIM0001" and back.meta["run"] == str(run) and back.meta["profile"] == "fast-thermal"
    assert np.array_equal(back.acc_g, out.acc_g) and np.array_equal(back.temp_c, out.temp_c)
    # chunks were compacted: sealed chunks of >= 1024 samples, not one row per block
    with db.session() as s:
        rows = s.execute(select(SampleChunk.n, SampleChunk.sealed).order_by(SampleChunk.seq)).all()
    assert all(sealed for _, sealed in rows)
    assert sum(n for n, _ in rows) == len(time_s) and len(rows) <= 5


def test_station_db_export_and_prune_commands(tmp_path, capsys):
    from cli.main import main

    db = sqlite_db(tmp_path)
    time_s, acc, temp = lis3dsh_stream(2000)
    batch, run, lamp, pos = _stream_run(db, time_s, acc, temp)
    url = str(db.engine.url)

    def station_db(*args):
        rc = main(["db", "--url", url, *args])
        out = capsys.readouterr()
        return rc, out.out, out.err

    rc, out, err = station_db("export", str(run), "--out", str(tmp_path / "x.csv"))
    assert rc == 0, err
    assert np.array_equal(read_log(tmp_path / "x.csv").acc_g, np.round(acc, ACC_DECIMALS))
    rc, out, err = station_db("export", "999", "--out", str(tmp_path / "y.csv"))
    assert rc == 2 and "no run 999" in err
    # too recent: nothing pruned
    rc, out, err = station_db("prune", "--older-than", "1")
    assert rc == 0 and "0 run(s)" in out, out + err
    rc, out, err = station_db("prune", "--older-than", "0", "--export", str(tmp_path / "archive"))
    assert rc == 0 and "1 run(s)" in out, out + err
    files = list((tmp_path / "archive").glob("*.csv"))
    assert len(files) == 1 and np.array_equal(read_log(files[0]).temp_c, np.round(temp, TEMP_DECIMALS))
    with db.session() as s:
        assert s.scalar(select(func.count(SampleChunk.id))) == 0
        assert s.scalar(select(func.count(SegmentRow.id))) == 1
        assert s.scalar(select(func.count(ThermalResultRow.id))) == 2
    assert repo.dut_by_serial(db, "SIM0001")["thermal"]["x"]["tdb_mg_per_c"] == 0.42
    with pytest.raises(StationError, match="pruned"):
        run_log(db, run)
    # a user's mistake from the real command line: one line on stderr, no traceback
    r = subprocess.run([sys.executable, "-m", "cli", "db", "--url", url, "export", str(run), "--out",
                        str(tmp_path / "z.csv")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "pruned" in r.stderr


def test_prune_selects_by_end_time_and_skips_running_runs(tmp_path):
    db = sqlite_db(tmp_path)
    time_s, acc, temp = lis3dsh_stream(300)
    _, old_run, _, _ = _stream_run(db, time_s, acc, temp, slot="a", serial="OLD")
    b2 = db.create_batch("fast-thermal", "t", {})
    live = db.create_run(b2, "b", "LIVE", "LIS3DSH", {}, state="running")
    w = DbWriter(db)
    w.bind_run(b2, "b", live)
    w.submit(SamplesReceived(b2, "b", "LIVE", 0, SampleBlock(time_s, acc, temp)))
    w.close()
    rep = prune(db, 10, now=utcnow() + timedelta(days=11))
    assert rep.runs == [old_run] and rep.bytes_deleted > 0
    assert len(run_log(db, live)) == len(time_s)
