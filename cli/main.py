"""`station` command line (design 5.2).

Each subcommand lives in its own module under cli/commands/ with two functions:
`add_arguments(parser)` and `run(args) -> int`. A user's mistake raises StationError and becomes
one line on stderr with exit code 2; no traceback. A reader that closes the pipe early (`| head`)
ends any command quietly with exit code 141 (128 + SIGPIPE), handled here once for all commands.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

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


# Commands whose linear algebra is thousands of small problems (a few thousand rows, a few dozen
# columns): OpenBLAS's worker threads only add hand-offs there, and on the 2-core station PC, with
# anything else running, they wait for each other (`station diagnose`: 2-3x the wall time, twice the
# CPU time). One BLAS thread gives the same numbers (measured: identical report).
ONE_BLAS_THREAD = frozenset({"diagnose"})
BLAS_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def _blas_threads(command: str) -> None:
    """One BLAS thread for the commands of ONE_BLAS_THREAD, unless the caller set the variables
    (BLAS reads them once, when numpy is first imported: a process that has numpy already, such
    as a test calling main() in-process, is left alone, and its environment is not changed)."""
    if command in ONE_BLAS_THREAD and "numpy" not in sys.modules:
        for var in BLAS_THREAD_VARS:
            os.environ.setdefault(var, "1")


class _CommandParser(argparse.ArgumentParser):
    """A subcommand's parser that imports its module (cli/commands/NAME.py) and adds its arguments
    only when the command is parsed or its help is shown: `station --help` and every other command
    never import what one command needs (scipy, matplotlib, the simulator, SQLAlchemy, the web)."""

    def __init__(self, *args, command: str | None = None, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._command = command  # None: a nested parser (e.g. `db export`), built by its command

    def _load(self) -> None:
        name, self._command = self._command, None
        if name is None:
            return
        _blas_threads(name)
        try:
            module = importlib.import_module(f"cli.commands.{name.replace('-', '_')}")
        except ModuleNotFoundError as exc:
            if exc.name and exc.name.startswith("cli.commands"):
                self.set_defaults(_module=None, _command=name)
                return
            raise
        module.add_arguments(self)
        self.set_defaults(_module=module, _command=name)

    def parse_known_args(self, args=None, namespace=None):  # type: ignore[override]
        self._load()
        return super().parse_known_args(args, namespace)

    def format_usage(self) -> str:
        self._load()
        return super().format_usage()

    def format_help(self) -> str:
        self._load()
        return super().format_help()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="station", description="MEMS accelerometer thermal calibration station")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_CommandParser)
    sub.required = True
    for name, help_text in COMMANDS.items():
        # the command's module is imported when the command is used (_CommandParser)
        sub.add_parser(name, help=help_text, description=help_text, command=name)
    return parser


# A closed pipe (`station calibrate LOG --json | head`) ends a command quietly with the exit code a
# shell reports for a process killed by SIGPIPE, as `yes | head` or `cat big | head` do.
SIGPIPE_EXIT = 128 + 13


def main(argv: list[str] | None = None) -> int:
    try:
        try:
            rc = _main(argv)
        except SystemExit:  # argparse's --help and usage errors print, then exit
            _flush()
            raise
        _flush()
        return rc
    except BrokenPipeError:
        closed = [s for s in (sys.stdout, sys.stderr) if _is_closed_pipe(s)]
        if not closed:  # a socket or pty of the station's own links: a real error, not the reader leaving
            raise
        for stream in closed:
            _point_at_devnull(stream)
        return SIGPIPE_EXIT


def _flush() -> None:
    """What is still buffered goes now, inside main's handler, not at interpreter exit (where a
    closed pipe would print "Exception ignored ... BrokenPipeError")."""
    for stream in (sys.stdout, sys.stderr):
        if stream is not None and not stream.closed:
            stream.flush()


def _is_closed_pipe(stream) -> bool:
    """stream's file is a pipe (or socket) whose reading end is gone (poll reports POLLERR)."""
    import select

    try:
        fd = stream.fileno()
    except (AttributeError, ValueError, OSError):  # None, closed, or not a file (a test's capture)
        return False
    if not hasattr(select, "poll"):  # no poll (Windows): a broken stdout is the usual cause
        return True
    poller = select.poll()
    poller.register(fd, select.POLLOUT)
    try:
        events = poller.poll(0)
    except OSError:
        return False
    return any(ev & select.POLLERR for _fd, ev in events)


def _point_at_devnull(stream) -> None:
    """The stream's file descriptor now goes to /dev/null: what Python still holds for it, written at
    exit, is dropped without a second error."""
    import os

    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, stream.fileno())
    finally:
        os.close(devnull)


def _main(argv: list[str] | None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    from contracts.types import StationError  # numpy: not imported by `station --help`

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
