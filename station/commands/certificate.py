"""`station certificate SERIAL [--db PATH|URL] [--config FILE] [--out FILE]`: the calibration
certificate (PDF) of a DUT's result run (station/records/certificate.py): identity, station, operator,
firmware, profile and limits version, coefficients with their expanded uncertainty, every check of
the verdict, program and verify, the ISO/IEC 17025 statements, and the fit plot.

--db takes a SQLite file path or any SQLAlchemy URL; without it, the URL comes from $STATION_DB_URL
or the station default, as for `station db`. The issuer (`[certificate]`) is the one stored with
the run's batch; --config prints that config's `[certificate]` instead (e.g. for runs stored before
the section was configured).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from contracts.types import StationError
from contracts.filenames import safe_name


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("serial", metavar="SERIAL", help="DUT serial number")
    parser.add_argument("--db", metavar="PATH", help="SQLite file or database URL (default: $STATION_DB_URL or "
                        "sqlite:///var/station.db)")
    parser.add_argument("--config", metavar="FILE", help="take the issuer ([certificate]) from this station config "
                        "instead of the one stored with the run's batch")
    parser.add_argument("--out", metavar="FILE", help="PDF to write (default: certificate-SERIAL.pdf)")


def db_url(value: str | None) -> str:
    from station.commands.db import database_url

    if not value:
        return database_url(argparse.Namespace())
    if "://" in value:
        return value
    path = Path(value)
    if not path.exists():
        raise StationError(f"{path}: no such database file")
    return f"sqlite:///{path.resolve()}"


def run(args: argparse.Namespace) -> int:
    from db.database import Database
    from station.records.certificate import certificate_for
    from station.records.certificate_pdf import render_pdf

    section = None
    if getattr(args, "config", None):
        from station.config import load_config

        section = load_config(args.config).certificate.model_dump()
    db = Database(db_url(args.db))
    try:
        db.check()
        try:
            cert = certificate_for(db, args.serial, certificate_config=section)
        except LookupError as exc:
            raise StationError(str(exc)) from None
        if cert is None:
            raise StationError(f"no DUT with serial {args.serial!r} in {db}")
        out = Path(args.out) if args.out else Path(f"certificate-{safe_name(args.serial)}.pdf")
        out.write_bytes(render_pdf(cert))
    finally:
        db.dispose()
    print(f"{out}: certificate {cert.certificate_id} of {cert.serial}, verdict {cert.verdict or 'not judged'}, "
          f"run {cert.run_id}, station {cert.station}, {len(cert.checks)} checks")
    return 0
