"""Shared checks of the replay-the-line tests (tests/test_replay_line*.py)."""

from __future__ import annotations

import json
from pathlib import Path

from replay_recorder import Script, all_fail_limits, record, station_cli

SPEED = "300"


def recorded_batch(tmp_path_factory, name: str, script: Script, state: str = "finished"):
    """(folder, url, recorded): a batch run by the daemon per `script` into a new SQLite file,
    which must have ended `state`."""
    folder = tmp_path_factory.mktemp(name)
    url = f"sqlite:///{folder / 'line.db'}"
    rec = record(url, script)
    assert rec["state"] == state, rec
    return folder, url, rec


def sensors_of(url: str, batch: int) -> list[str]:
    """The sensor of every DUT of a recorded batch, as the replay reads it."""
    from station.replay.recording import from_database

    return [d.identity.sensor for d in from_database(url, batch).duts]


def replay(url: str, batch: int, out: Path, *extra: str):
    """`station replay` of a recorded batch; (completed process, the comparison JSON)."""
    p = station_cli("replay", "--db", url, "--batch", str(batch), "--speed", SPEED, "--json", str(out), *extra)
    diff = json.loads(out.read_text()) if out.exists() else None
    return p, diff


def assert_unchanged(p, diff, recorded: dict) -> None:
    """Exit 0, every DUT of the recording replayed with the identical samples and no change."""
    assert p.returncode == 0, p.stdout + p.stderr
    assert diff is not None
    assert {d["slot"] for d in diff["duts"]} == set(recorded["slots"]), diff["duts"]
    for d in diff["duts"]:
        assert d["changed"] is False and d["changes"] == [], (d["slot"], d["changes"], d["note"])
        assert d["samples_identical"] is True, d
        assert d["compared"] >= 3  # state, verdict, grade at least
    assert diff["summary"]["changed"] == 0 and diff["end_changed"] is False
    assert "Traceback" not in p.stderr


def assert_tight_limits_name_the_changed_verdicts(url: str, batch: int, folder: Path, recorded: dict):
    """The same recording under a limits set no part meets: every part recorded pass/marginal is
    named as changed to fail, exit 1; a part recorded error stays error."""
    cfg = all_fail_limits(folder / "tight.toml", sensors_of(url, batch))
    p, diff = replay(url, batch, folder / "tight.json", "--config", cfg)
    judged = {s["serial"]: s["verdict"] for s in recorded["slots"].values()}
    expect = sorted(s for s, v in judged.items() if v in ("pass", "marginal"))
    assert expect, judged
    notes = "\n".join(f"{d['slot']}: {d['note']}" for d in (diff or {}).get("duts", []))
    assert p.returncode == 1, p.stdout + p.stderr + notes
    for serial in expect:
        assert f"verdict changed: {serial} {judged[serial]} -> fail" in p.stdout, p.stdout + notes
    named = sorted(v["serial"] for v in diff["summary"]["verdicts_changed"])
    assert named == expect, (named, judged)
    return diff
