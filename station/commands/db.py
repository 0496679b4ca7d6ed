"""`station db upgrade|export|prune`: schema migration, one run's log CSV, sample retention.

The database URL comes from --url, else $STATION_DB_URL, else `database_url` of --config FILE
(station TOML), else the station's default sqlite:///var/station.db.
"""

from __future__ import annotations

import argparse
import os
import tomllib
from pathlib import Path

from contracts.types import StationError

DEFAULT_URL = "sqlite:///var/station.db"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--url", help="database URL (default: $STATION_DB_URL or the config's database_url)")
    parser.add_argument("--config", metavar="FILE", help="station TOML config to take database_url from")
    sub = parser.add_subparsers(dest="db_command", metavar="ACTION")
    sub.required = True
    sub.add_parser("upgrade", help="migrate the database to this software's schema")
    sub.add_parser("check", help="check the schema revision without changing anything")
    p = sub.add_parser("export", help="write one run's sample log (design 5.1 CSV)")
    p.add_argument("run_id", type=int, metavar="RUN_ID")
    p.add_argument("--out", required=True, metavar="FILE", help="CSV file to write")
    p = sub.add_parser("prune", help="delete old runs' sample streams, keeping segments and results")
    p.add_argument("--older-than", type=float, required=True, metavar="DAYS", help="runs that ended more than DAYS ago")
    p.add_argument("--export", metavar="DIR", help="first write each run's log CSV into DIR")
    p.add_argument("--vacuum", action="store_true", help="SQLite: give the freed space back to the file system")


def database_url(args: argparse.Namespace) -> str:
    if getattr(args, "url", None):
        return args.url
    if os.environ.get("STATION_DB_URL"):
        return os.environ["STATION_DB_URL"]
    if getattr(args, "config", None):
        path = Path(args.config)
        try:
            data = tomllib.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise StationError(f"{path}: no such file") from None
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            raise StationError(f"{path}: cannot read config ({exc})") from None
        url = data.get("database_url") or (data.get("db") or {}).get("url")
        if url:
            return str(url)
    return DEFAULT_URL


def run(args: argparse.Namespace) -> int:
    from db.database import Database
    from db.export import export_run_csv, prune

    db = Database(database_url(args))
    try:
        if args.db_command == "upgrade":
            before = db.current_revision()
            rev = db.upgrade()
            print(f"database at schema revision {rev}" + ("" if before == rev else f" (was {before or 'empty'})"))
            return 0
        if args.db_command == "check":
            print(f"database at schema revision {db.check()} (current)")
            return 0
        db.check()
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
