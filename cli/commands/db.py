"""`station db upgrade|check|export|prune`: schema migration, one run's log CSV, sample retention.

The database URL comes from --url (a URL or a SQLite file path), else $STATION_DB_URL, else
`database_url` of --config FILE (station TOML), else the station's default sqlite:///var/station.db.
Only `upgrade` creates a database (that is its job); check, export and prune open an existing one
(check and export read-only) and name where they looked when there is none
(cli/commands/db_source.py).
"""

from __future__ import annotations

import argparse

from contracts.types import StationError
from cli.commands.db_source import choose_from_args, open_existing, plain_url


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--url", help="database URL or SQLite file (default: $STATION_DB_URL, the config's "
                        "database_url, else ./var/station.db); only upgrade creates one")
    parser.add_argument("--config", metavar="FILE", help="station TOML config to take database_url from")
    sub = parser.add_subparsers(dest="db_command", metavar="ACTION")
    sub.required = True
    sub.add_parser("upgrade", help="migrate the database to this software's schema (creating it if needed)")
    sub.add_parser("check", help="check the schema revision without changing anything")
    p = sub.add_parser("export", help="write one run's sample log (design 5.1 CSV)")
    p.add_argument("run_id", type=int, metavar="RUN_ID")
    p.add_argument("--out", required=True, metavar="FILE", help="CSV file to write")
    p = sub.add_parser("prune", help="delete old runs' sample streams, keeping segments and results")
    p.add_argument("--older-than", type=float, required=True, metavar="DAYS", help="runs that ended more than DAYS ago")
    p.add_argument("--export", metavar="DIR", help="first write each run's log CSV into DIR")
    p.add_argument("--vacuum", action="store_true", help="SQLite: give the freed space back to the file system")


def run(args: argparse.Namespace) -> int:
    from db.database import Database
    from db.export import export_run_csv, prune

    choice = choose_from_args(args, "url", "--url")
    if args.db_command == "upgrade":  # the one action that may create the database
        try:
            db = Database(choice.url)
        except Exception as exc:  # noqa: BLE001 - a URL SQLAlchemy cannot parse or has no driver for
            raise StationError(f"database {plain_url(choice.url)}: {type(exc).__name__}: {exc}") from None
        try:
            before = db.current_revision()
            rev = db.upgrade()
        finally:
            db.dispose()
        print(f"database {plain_url(choice.url)} at schema revision {rev}"
              + ("" if before == rev else f" (was {before or 'empty'})"))
        return 0
    db = open_existing(choice, write=args.db_command == "prune")  # checked: at this software's schema
    try:
        if args.db_command == "check":
            print(f"database {plain_url(choice.url)} at schema revision {db.head_revision()} (current)")
            return 0
        if args.db_command == "export":
            try:
                path = export_run_csv(db, args.run_id, args.out)
            except KeyError:
                raise StationError(f"no run {args.run_id} in the database") from None
            except OSError as exc:
                raise StationError(f"cannot write {args.out}: {exc}") from None
            print(f"run {args.run_id} written to {path}")
            return 0
        if args.db_command == "prune":
            rep = prune(db, args.older_than, export_dir=args.export, vacuum=args.vacuum)
            print(
                f"pruned the samples of {len(rep.runs)} run(s) that ended before {rep.cutoff:%Y-%m-%d %H:%M} UTC: "
                f"{rep.chunks_deleted} chunks, {rep.bytes_deleted} bytes"
                + (f"; {len(rep.files)} CSV file(s) in {args.export}" if args.export else "")
            )
            return 0
        raise StationError(f"unknown action {args.db_command}")
    finally:
        db.dispose()
