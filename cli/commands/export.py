"""`station export FORMAT (--batch ID | --run ID) [--db PATH|URL] [--config FILE] --out FILE`:
a stored batch (every DUT run) or one run, with every verdict and every judged measurement, in a
registered export format (station/records/export_formats.py: `stdf` STDF V4, `ocptv` OCP Test &
Validation JSON lines, ...) for a factory's yield and traceability tools (docs/exports.md).

--db takes a SQLite file path or any SQLAlchemy URL; without it the URL comes from --config
(`database_url`), $STATION_DB_URL or the station default, as for `station db`; the database must
exist (it is opened read-only, never created or migrated: cli/commands/db_source.py). A batch
still running is refused (its verdicts are not final), as is an unknown id.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from contracts.types import StationError
from station.records.export_formats import export_format, export_formats


def add_arguments(parser: argparse.ArgumentParser) -> None:
    formats = export_formats()  # as registered when the parser is built
    parser.add_argument("format", choices=tuple(formats),
                        help="; ".join(f"{f.name}: {f.help or f.title}" for f in formats.values()))
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument("--batch", type=int, metavar="ID", help="every DUT run of this batch")
    which.add_argument("--run", type=int, metavar="ID", help="this DUT run only")
    parser.add_argument("--db", metavar="PATH", help="SQLite file or database URL, which must exist "
                        "(default: $STATION_DB_URL, the config's, else ./var/station.db if it is there)")
    parser.add_argument("--config", metavar="FILE", help="station config to take database_url from")
    parser.add_argument("--out", metavar="FILE", required=True, help="file to write")


def run(args: argparse.Namespace) -> int:
    from cli.commands.db_source import choose_from_args, open_existing
    from station.records.export_model import ExportNotFound, ExportNotReady, load_report

    fmt = export_format(args.format)
    for ident in (args.batch, args.run):
        if ident is not None and ident < 1:
            raise StationError(f"an id is a positive number, not {ident}")
    db = open_existing(choose_from_args(args))
    try:
        try:
            report = load_report(db, batch_id=args.batch, run_id=args.run)
        except (ExportNotFound, ExportNotReady) as exc:
            raise StationError(str(exc).strip("'\"")) from None
    finally:
        db.dispose()
    data = fmt.write(report)
    out = Path(args.out)
    try:
        out.write_bytes(data)
    except OSError as exc:
        raise StationError(f"{out}: cannot write ({exc.strerror or exc})") from None
    counts = {v: sum(1 for p in report.parts if p.verdict == v) for v in ("pass", "marginal", "fail", "error")}
    what = f"batch {report.batch_id}" if args.batch is not None else f"run {args.run} of batch {report.batch_id}"
    n_tests = sum(len(p.tests) for p in report.parts)
    print(f"{out}: {fmt.title} of {what}: {len(report.parts)} parts ("
          + ", ".join(f"{n} {v}" for v, n in counts.items() if n) + f"), {n_tests} measurements, {len(data)} bytes")
    return 0
