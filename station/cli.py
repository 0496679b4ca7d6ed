"""`station` command line (design 5.2).

Each subcommand lives in its own module under station/commands/ with two functions:
`add_arguments(parser)` and `run(args) -> int`. A user's mistake raises StationError and becomes
one line on stderr with exit code 2; no traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from contracts.types import StationError

COMMANDS: dict[str, str] = {
    "demo": "a whole simulated station on this machine, serving the operator page",
    "serve": "the station daemon with real hardware as configured",
    "simulate": "write logs of simulated DUTs with their true parameters",
    "calibrate": "thermal calibration (TDB/TDSF) of a recorded fast-thermal log",
    "sfem": "sensor frame error model fit of static positions",
    "diagnose": "compare the thermal model with a log, rank missing effects, add them",
    "replay": "run a recorded batch (or logs) again through simulated boards and diff the outcome",
    "certificate": "calibration certificate (PDF) of a DUT by serial number",
    "export": "a stored batch or run as STDF V4 or OCP Test & Validation JSON for yield tools",
    "db": "database maintenance: upgrade, export and prune sample streams",
}


def one_line(text: str) -> str:
    """An error stays one line: control characters (a corrupted SQLite file's bytes can reach its
    error text, and str.splitlines() breaks on \x1c) are written as escapes."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="station", description="MEMS accelerometer thermal calibration station")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name, help_text in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        try:
            module = importlib.import_module(f"station.commands.{name.replace('-', '_')}")
        except ModuleNotFoundError as exc:
            if exc.name and exc.name.startswith("station.commands"):
                p.set_defaults(_module=None, _command=name)
                continue
            raise
        module.add_arguments(p)
        p.set_defaults(_module=module, _command=name)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args._module is None:
        print(f"station {args._command}: not available in this build", file=sys.stderr)
        return 2
    try:
        return int(args._module.run(args) or 0)
    except StationError as exc:
        print(f"station {args._command}: error: {one_line(str(exc))}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"station {args._command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
