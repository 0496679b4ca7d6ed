"""`station certificate SERIAL [--db PATH|URL] [--config FILE] [--out FILE]`: the calibration
certificate (PDF) of a DUT's result run (station/records/certificate.py): identity, station, operator,
firmware, profile and limits version, coefficients with their expanded uncertainty, every check of
the verdict, program and verify, the ISO/IEC 17025 statements, and the fit plot.

--db takes a SQLite file path or any SQLAlchemy URL; without it, the URL comes from $STATION_DB_URL
or the station default, as for `station db` (cli/commands/db_source.py). The database is only
read: opened read-only, never created (a missing file is one line and exit 2), never migrated.
The issuer (`[certificate]`) is the one stored with the run's batch; --config prints that config's
`[certificate]` instead (e.g. for runs stored before the section was configured).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from contracts.types import StationError
from contracts.filenames import safe_name


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("serial", metavar="SERIAL", help="DUT serial number")
    parser.add_argument("--db", metavar="PATH", help="SQLite file or database URL, which must exist (default: "
                        "$STATION_DB_URL, else ./var/station.db if it is there)")
    parser.add_argument("--config", metavar="FILE", help="take the issuer ([certificate]) from this station config "
                        "instead of the one stored with the run's batch")
    parser.add_argument("--out", metavar="FILE", help="PDF to write (default: certificate-SERIAL.pdf)")


def run(args: argparse.Namespace) -> int:
    from cli.commands.db_source import choose, open_existing, plain_url
    from station.records.certificate import certificate_for
    from station.records.certificate_pdf import render_pdf

    section = None
    if getattr(args, "config", None):
        from station.config import load_config

        section = load_config(args.config).certificate.model_dump()
    choice = choose(args.db)
    db = open_existing(choice)
    try:
        try:
            cert = certificate_for(db, args.serial, certificate_config=section)
        except LookupError as exc:
            raise StationError(str(exc)) from None
        if cert is None:
            raise StationError(f"no DUT with serial {args.serial!r} in {plain_url(choice.url)}")
        out = Path(args.out) if args.out else Path(f"certificate-{safe_name(args.serial)}.pdf")
        out.write_bytes(render_pdf(cert))
    finally:
        db.dispose()
    print(f"{out}: certificate {cert.certificate_id} of {cert.serial}, verdict {cert.verdict or 'not judged'}, "
          f"run {cert.run_id}, station {cert.station}, {len(cert.checks)} checks")
    return 0
