"""Replay reproduces what the line did (issue 22): a batch run from the page with the operator
turning the plate at the prompts (no fixture), and a batch the operator aborted.

Each batch is recorded in the test by the real daemon on simulated boards (tests/replay_recorder.py),
then replayed by `station replay` in a subprocess: it must come out unchanged (the boards sent the
recorded counts bit for bit, every stored figure and word equal, exit 0), and with a limits set
no part meets it must exit 1 naming every changed verdict. Independent truth: the recorded rows
(prompts answered, position column, the batch's end state) read back from the database.
"""

from __future__ import annotations

import pytest

from replay_line_checks import (assert_tight_limits_name_the_changed_verdicts, assert_unchanged, recorded_batch,
                                replay, sensors_of)
from replay_recorder import Script, all_fail_limits


@pytest.fixture(scope="module")
def page_batch(tmp_path_factory):
    return recorded_batch(tmp_path_factory, "page", Script(profile="fast-thermal", fixture=False))


def test_a_page_batch_with_operator_prompts_and_no_fixture_replays_unchanged(page_batch):
    folder, url, rec = page_batch
    from station.replay.recording import from_database

    r = from_database(url, rec["batch"])
    assert r.config_snapshot.get("fixture") is None  # the recorded station had no fixture
    pos = r.duts[0].position
    assert (pos == -1).any() and (pos == 0).any() and (pos == 1).any()  # the operator turned P, then N
    p, diff = replay(url, rec["batch"], folder / "same.json")
    assert_unchanged(p, diff, rec)
    answered = [n for n in diff["notes"] if "answered at the recorded answer" in n]
    assert len(answered) == 2, diff["notes"]  # "turn the plate to P", then "to N"
    assert diff["replay_state"] == "finished" and diff["agreement"]["agrees"] is True, diff["agreement"]


def test_a_page_batch_under_another_limits_set_names_the_changed_verdicts(page_batch):
    folder, url, rec = page_batch
    assert_tight_limits_name_the_changed_verdicts(url, rec["batch"], folder, rec)


@pytest.fixture(scope="module")
def aborted_batch(tmp_path_factory):
    return recorded_batch(tmp_path_factory, "aborted", Script(profile="fast-thermal", abort_at_sample_s=2500.0),
                          state="aborted")


def test_an_aborted_batch_replays_to_where_the_recording_ends_unchanged(aborted_batch):
    folder, url, rec = aborted_batch
    p, diff = replay(url, rec["batch"], folder / "same.json")
    assert_unchanged(p, diff, rec)
    assert diff["recorded_state"] == "aborted" and diff["replay_state"] == "aborted"
    assert diff["ended_at_recording_end"] is True
    assert "batch ended where the recording ends, as recorded (aborted)" in " ".join(p.stdout.split())
    assert "safety trip" not in p.stdout + p.stderr
    # every recorded sample was sent (the replay ran to the end of the recording, not beyond)
    for d in diff["duts"]:
        sent, of = [int(x) for x in d["note"].split(" recorded")[0].split("sent ")[1].split(" of ")]
        assert sent == of, d["note"]


def test_an_aborted_batch_has_no_verdict_a_limits_set_could_change(aborted_batch):
    """Every run of an aborted batch is error (design 8), whatever the limits: the replay under a
    limits set no part meets changes nothing and says so with exit 0."""
    folder, url, rec = aborted_batch
    assert {s["verdict"] for s in rec["slots"].values()} == {"error"}
    cfg = all_fail_limits(folder / "t.toml", sensors_of(url, rec["batch"]))
    p, diff = replay(url, rec["batch"], folder / "tight.json", "--config", cfg)
    assert p.returncode == 0, p.stdout + p.stderr
    assert diff["summary"]["verdicts_changed"] == []
    assert all(d["changed"] is False for d in diff["duts"])
