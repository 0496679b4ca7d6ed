"""`station replay`: run a recorded batch again through simulated boards and diff the outcome.

    station replay --db sqlite:///var/station.db --batch 12            # a stored batch
    station replay --logs a.csv b.csv --profile fast-thermal           # design-5.1 logs
    station replay --db ... --batch 12 --config new-limits.toml --json out.json

Each recorded DUT becomes a simulated board that streams exactly the recorded samples (counts,
identity, sample clock) over pty serial / slcan CAN; the lamp relay and fixture on Modbus accept
the daemon's commands and report whether they agree with the recording. The replay is stored as
its own batch (marked replay, never sent to the MES) and compared with the recorded outcome.
Exit 0: nothing changed beyond the tolerance; 1: something changed (a release gate); 2: error.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import tomllib
from pathlib import Path

from station.replay.compare import DEFAULT_ATOL, DEFAULT_RTOL, ReplayDiff
from contracts.types import StationError


def add_arguments(p: argparse.ArgumentParser) -> None:
    src = p.add_argument_group("source (one of)")
    src.add_argument("--batch", type=int, default=None, help="id of a stored batch (in --source-db, default --db)")
    src.add_argument("--logs", nargs="+", default=None, metavar="CSV", help="design-5.1 logs, one per DUT")
    p.add_argument("--db", default=None, help="database (URL or SQLite file) the replay batch is stored in "
                   "(default: the source database; sqlite:///./var/replay.db for logs); with --batch and no "
                   "--source-db it is also the source, which must exist")
    p.add_argument("--source-db", default=None, help="database holding --batch, e.g. a copy from another station; "
                   "only read, never created")
    p.add_argument("--profile", default=None, help="profile to run (default: the recorded one)")
    p.add_argument("--config", default=None, metavar="TOML",
                   help="take limits, products, profiles and timing from this station config instead")
    p.add_argument("--only", nargs="+", default=None, metavar="SERIAL", help="replay these serials (or slots) only")
    p.add_argument("--speed", type=float, default=60.0, help="sample seconds per wall second (default 60)")
    p.add_argument("--rtol", type=float, default=DEFAULT_RTOL, help=f"relative tolerance (default {DEFAULT_RTOL:g})")
    p.add_argument("--atol", type=float, default=DEFAULT_ATOL, help=f"absolute tolerance (default {DEFAULT_ATOL:g})")
    p.add_argument("--agree-window", type=float, default=None, metavar="S",
                   help="sample seconds a lamp/fixture disagreement may last before it is reported "
                        "(default: the larger of 120 and 1 s x speed, the resolution of compressed time)")
    p.add_argument("--fail-on-plate", action="store_true",
                   help="exit 1 also when the lamp or fixture disagreed with the recording")
    p.add_argument("--json", dest="json_out", default=None, metavar="FILE", help="write the comparison as JSON ('-' stdout)")
    p.add_argument("--verbose", "-v", action="store_true")


def _overrides(path: str | None) -> dict | None:
    if path is None:
        return None
    from station.config import load_config

    load_config(path)  # the whole file must be a valid config (one clear line if not)
    return tomllib.loads(Path(path).read_text(encoding="utf-8"))


def load_recording(args: argparse.Namespace):
    from station.replay import recording as rec

    if (args.batch is None) == (args.logs is None):
        raise StationError("give exactly one source: --batch ID or --logs CSV...")
    if args.batch is not None:
        from cli.commands.db_source import choose, require_existing

        flag, given = ("--source-db", args.source_db) if args.source_db else ("--db", args.db)
        if not given:
            raise StationError("no database given: --batch ID is read from the database it is in: give --db "
                               "(or --source-db) PATH|URL; a replay has no default database")
        src = choose(given, flag)
        require_existing(src)  # the source is only read: a missing file is one line, nothing created
        r = rec.from_database(src.url, args.batch)
        if args.profile:
            r.profile = args.profile
    else:
        r = rec.from_logs(args.logs, args.profile)
    return r.only(args.only)


def print_table(diff: ReplayDiff) -> None:
    from rich.console import Console
    from rich.table import Table

    console = Console(highlight=False)
    s = diff.summary()
    t = Table(title=f"replay of {diff.source}  (before: {diff.before_label}; batch {diff.replay_batch_id} "
                    f"{diff.replay_state})")
    for col in ("slot", "serial", "samples", "changed", "what changed (before -> after)"):
        t.add_column(col)
    for d in diff.duts:
        what = "; ".join(f"{c.key} {_v(c.before)} -> {_v(c.after)}" for c in d.changes[:6])
        if len(d.changes) > 6:
            what += f"; +{len(d.changes) - 6} more"
        same = {True: "identical", False: "DIFFERENT", None: "-"}[d.samples_identical]
        t.add_row(d.slot, d.serial, same, "yes" if d.changed else "no", what or "-")
    console.print(t)
    line = f"{s['duts']} DUTs: {s['unchanged']} unchanged, {s['changed']} changed"
    if s["largest_change"]:
        c = s["largest_change"]
        line += f"; largest {c['serial']} {c['key']} {_v(c['before'])} -> {_v(c['after'])}"
    console.print(line)
    for v in s["verdicts_changed"]:
        console.print(f"verdict changed: {v['serial']} {v['before']} -> {v['after']}")
    ag = diff.agreement
    for dev in ("lamp", "fixture"):
        a = ag.get(dev)
        if a:
            state = "agrees" if a["agrees"] else f"DISAGREES ({len(a['episodes'])} episodes, {a['disagree_s']:.0f} s)"
            console.print(f"{dev}: {state} with the recording (compared over {a['checked_s']:.0f} s, "
                          f"episodes shorter than {ag.get('window_s', 0):.0f} s of sample time ignored)")
            for ep in a["episodes"]:
                console.print(f"  {ep.get('explanation') or ep}")
    if ag.get("note"):
        console.print(ag["note"])
    for note in diff.notes:
        console.print(f"replay: {note}")
    if diff.ended_at_recording_end and not diff.end_changed:
        console.print(f"batch ended where the recording ends, as recorded ({diff.recorded_state})")
    rate = ag.get("rate") or {}
    if rate:
        console.print(f"replayed {rate['samples_sent']} samples in {rate['wall_s']} s wall "
                      f"({rate['samples_per_s']} samples/s)")


def _v(x) -> str:
    if isinstance(x, float):
        return f"{x:.6g}"
    return str(x)


def run(args: argparse.Namespace) -> int:
    from cli.runtime import setup_logging
    from station.replay.runner import ReplayOptions, run_replay

    setup_logging(args.verbose)
    if args.speed <= 0:
        raise StationError("--speed must be > 0")
    from cli.commands.db_source import to_url

    recording = load_recording(args)
    # a SQLite file path is taken as well as a URL; the replay's own --db (beside --source-db) is
    # its results database and may be created, the source never is (load_recording)
    args.db, args.source_db = (to_url(v) if v else v for v in (args.db, args.source_db))
    db_url = args.db or args.source_db or f"sqlite:///{Path('var').resolve() / 'replay.db'}"
    if recording.source_note and db_url == (args.source_db or args.db):
        raise StationError(f"batch {args.batch}: its database has an older schema and a replay never migrates "
                           "its source: give --source-db for it and --db for the replay's results "
                           "(e.g. --db sqlite:///var/replay.db)")
    if db_url.startswith("sqlite:///") and not args.db and not args.source_db:
        Path("var").mkdir(exist_ok=True)
    opts = ReplayOptions(db_url=db_url, speed=args.speed, overrides=_overrides(args.config), rtol=args.rtol,
                         atol=args.atol, agree_window_s=args.agree_window)
    for note in recording.skipped:
        print(f"station replay: not replayed: {note}", file=sys.stderr)
    if recording.source_note:
        print(f"station replay: source {recording.source_note}", file=sys.stderr)
    print(f"station replay: {recording.source}: {len(recording.duts)} DUTs, profile {recording.profile}, "
          f"speed x{args.speed:g}", file=sys.stderr, flush=True)
    diff = asyncio.run(run_replay(recording, opts))
    if args.json_out:
        text = json.dumps(diff.to_json(), indent=2)
        if args.json_out == "-":
            print(text)
        else:
            Path(args.json_out).write_text(text)
    if args.json_out != "-":
        print_table(diff)
    plate_bad = args.fail_on_plate and diff.agreement.get("agrees") is False
    if diff.end_changed:
        print(f"batch ended {diff.replay_state} ({diff.replay_error or '-'}), the recorded one {recording.batch_state}"
              + (f" ({recording.batch_error})" if recording.batch_error else ""))
    return 1 if diff.changed or diff.end_changed or plate_bad else 0
