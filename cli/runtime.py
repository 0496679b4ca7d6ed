"""What a long-running command (serve, demo, replay) sets up for its process: logging to stderr and
the stop signals. The web server's start and stop are web/server.py's."""

from __future__ import annotations

import asyncio
import logging
import sys


def install_stop_signals(stop: asyncio.Event) -> None:
    """SIGINT and SIGTERM set `stop` (the command then switches the lamp off first and ends)."""
    import signal

    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            loop.add_signal_handler(sig, stop.set)
        except (NotImplementedError, RuntimeError):
            pass


def setup_logging(verbose: bool) -> None:
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not verbose:  # errors reach the user as one StationError line, not library chatter
        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


__all__ = ["install_stop_signals", "setup_logging"]
