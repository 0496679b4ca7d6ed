"""One board firmware process (firmware/build/host/fwboard) on a real pty, fed by a sensor bridge.

Shared by tests/test_firmware_host.py and tests/test_firmware_records.py. The station side reads
the pty slave itself; frames are checked with the station's own codec (drivers/protocol/
serial_frames.py). The trailing `key=value` fields of the `I` and `C` frames (docs/design.md
3.1) are taken off before that codec sees a frame and kept in `keys`, so the checks of
the base protocol stay exact whether or not the station's codec knows the keys.
"""

from __future__ import annotations

import os
import select
import signal
import socket
import subprocess
import time
import tty
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

import pytest

from contracts.types import Identity
from drivers.sim.firmware_build import build, missing_tools
from drivers.protocol import serial_frames as sf

SAMPLE_STEP_US = 320_000  # the 3.125 Hz source period of the identities the tests use


def split_keys(fields: list[str]) -> tuple[list[str], dict[str, str]]:
    """A frame's fields without its trailing key=value fields, and those as a dict (in order)."""
    n = len(fields)
    while n > 1 and "=" in fields[n - 1]:
        n -= 1
    return fields[:n], dict(f.split("=", 1) for f in fields[n:])


def bodies(raw: bytes) -> list[list[str]]:
    """Every `$BODY*HH` line of raw, checksum verified (upper-case HH), as its comma fields."""
    out = []
    for line in raw.split(b"\n"):
        if not line:
            continue
        assert line[:1] == b"$" and line[-3:-2] == b"*", line
        body, hh = line[1:-3], line[-2:]
        assert hh == b"%02X" % sf.checksum(body), line
        out.append(body.decode("ascii").split(","))
    return out


class FwProc:
    """One board process: pty master to the child, the slave kept open here (raw), a socketpair bridge."""

    def __init__(self, exe: Path, ident: Identity, nvm: Path, *, can: int | None = None, tear: int | None = None,
                 fw: str | None = None) -> None:
        master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.bridge, child = socket.socketpair()
        args = [str(exe), "--uart-fd", str(master), "--bridge-fd", str(child.fileno()), "--nvm", str(nvm)]
        if can is not None:
            args += ["--can", str(can)]
        if tear is not None:
            args += ["--nvm-tear-after", str(tear)]
        if fw is not None:
            args += ["--fw", fw]
        self.proc = subprocess.Popen(args, pass_fds=(master, child.fileno()))
        os.close(master)
        child.close()
        self.ident = ident
        self.t_us = 0
        self.keys: dict[str, dict[str, str]] = {}  # frame kind ("I", "C") -> its last trailing keys
        i = ident
        self.bridge.sendall(sf.encode(f"B,{i.serial},{i.sensor},{sf.fmt_number(i.ug_per_lsb)},"
                                      f"{sf.fmt_number(i.t_lsb_per_c)},{sf.fmt_number(i.t_lsb_at_25c)},{sf.fmt_number(i.odr_hz)}"))
        self.bridge.settimeout(5)
        assert self.bridge.recv(64) == sf.encode("READY")

    def feed(self, acc: Any, temp: Any, t_us: Any = None) -> list[int]:
        """Samples (n,3) counts and (n,) temperature counts, at t_us (default: one source period
        apart, after the previous); returns their t_us."""
        out, ts = [], []
        times = None if t_us is None else [int(t) for t in t_us]
        for k, (a, t) in enumerate(zip(np.asarray(acc).tolist(), np.asarray(temp).tolist())):
            if times is not None:
                self.t_us = times[k]
            ts.append(self.t_us)
            out.append(sf.encode(f"S,{self.t_us},{a[0]},{a[1]},{a[2]},{t}"))
            self.t_us += SAMPLE_STEP_US
        self.bridge.sendall(b"".join(out))
        return ts

    def write(self, raw: bytes) -> None:
        os.write(self.slave, raw)

    def read_until(self, done: Callable[[bytes], bool], timeout: float = 5.0) -> bytes:
        buf = b""
        end = time.monotonic() + timeout
        while not done(buf) and time.monotonic() < end:
            r, _, _ = select.select([self.slave], [], [], 0.05)
            if r:
                try:
                    buf += os.read(self.slave, 65536)
                except OSError:
                    break
        return buf

    def frames(self, raw: bytes) -> list[Any]:
        """The station codec's frames of raw (I and C frames without their trailing keys)."""
        plain = []
        for fields in bodies(raw):
            if fields[0] in ("I", "C"):
                fields, keys = split_keys(fields)
                self.keys[fields[0]] = keys
            plain.append(sf.encode(",".join(fields)))
        p = sf.FrameParser()
        got = p.feed(b"".join(plain))
        assert p.stats.frames_bad_checksum == 0 and p.stats.frames_malformed == 0, raw
        return got

    def command(self, body: str, n_frames: int = 1) -> list[Any]:
        self.write(sf.encode(body))
        return self.frames(self.read_until(lambda b: b.count(b"\n") >= n_frames))

    def command_fields(self, body: str, n_frames: int = 1, timeout: float = 5.0) -> list[list[str]]:
        """The raw fields of the reply frames (new frame kinds the station codec may not know)."""
        self.write(sf.encode(body))
        return bodies(self.read_until(lambda b: b.count(b"\n") >= n_frames, timeout))

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            rc = self.proc.wait(5)
        finally:
            self.bridge.close()
            os.close(self.slave)
        return rc


# ---- fixtures shared by the test files that run fwboard processes (imported there by name) -----

@pytest.fixture(scope="module")
def fwboard():
    """The host target's fwboard, built once per module (skipped without a C compiler)."""
    if missing_tools("host"):
        pytest.skip(f"no {missing_tools('host')}")
    return build("host") / "fwboard"


@pytest.fixture
def procs():
    """The fwboard processes a test started, killed at its end."""
    started: list[FwProc] = []
    yield started
    for p in started:
        if p.proc.poll() is None:
            p.proc.kill()
            p.proc.wait(5)


def _spawn(procs, *a, **kw) -> FwProc:
    p = FwProc(*a, **kw)
    procs.append(p)
    return p
