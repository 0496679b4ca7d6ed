"""Boards that run the reference firmware (firmware/, C) instead of the Python board model.

The world simulator still owns the physics (lamp, plate, positions, the DUT's true drift); a
firmware board only gets what its sensor would measure, over a *sensor bridge* (a second link,
design of firmware/README.md):

    $B,<serial>,<sensor>,<ug_per_lsb>,<t_lsb_per_c>,<t_lsb_at_25c>,<odr_hz>*HH   once, the strap
    $S,<t_us>,<ax>,<ay>,<az>,<t>*HH                                             one per sample

and answers `$READY*HH` on it once booted. Everything the station sees (framing, identity, ODR,
sample clock, NVM with CRC, compensation, the CAN twin) is the C firmware's own doing.

Recovery (issue 42, firmware/core/fw_bridge.h): a board sends `$BOOT*HH` when it starts
(after a watchdog or fault reset too), and the simulator answers with the strap again; `$INIT*HH`
when it (re-)initialises its sensor. Tests inject faults through the bridge: `sensor_reset()` (the
simulated sensor resets itself and sends nothing until the board's `$INIT`; its sample clock runs
on, so the samples it could not deliver are lost and the board's seq must show them),
`inject("hardfault")`, `inject("hang")`, `selfcal_skew(mg_per_c)` (`$X,...`).

Two ways to run one, with the same interface as drivers/sim/serial_pty.SimSerialBoard so that
SimStation puts them in slots beside the Python boards:
  host   `firmware/build/host/fwboard`, one Linux process per board; the station link is a pty
         this module creates (the station opens its slave like a USB CDC port), the bridge a
         socketpair; NVM in a file. A CAN node (`--can N`) speaks slcan-style lines on its link
         and joins the simulated bus behind the slcan adapter (FirmwareCanBoard).
  qemu   `firmware/build/qemu/fw.elf` on `qemu-system-arm -M netduinoplus2`: USART1 on
         `-serial pty` (the station opens the pty QEMU made), USART2 the bridge on a unix socket,
         NVM through semihosting in the board's own folder.
A power cycle kills the process (power lost mid-anything) and starts it again on the same NVM.
"""

from __future__ import annotations

import asyncio
import os
import re
import shutil
import signal
import socket
import subprocess
import tempfile
import threading
import tty
from collections.abc import Callable
from pathlib import Path

import numpy as np

from contracts.types import Identity
from drivers.protocol import serial_frames as sf
from drivers.sim.firmware_build import build, missing_tools

KINDS = ("host", "qemu")
BOOT_TIMEOUT_S = 20.0
BRIDGE_SNDBUF_BYTES = 8192
QEMU_PTY_RE = re.compile(rb"char device redirected to (/dev/pts/\d+) \(label serial0\)")


def strap_frame(identity: Identity) -> bytes:
    """The bridge's first frame: which sensor (and serial number) this board carries."""
    return sf.encode("B,%s,%s,%s,%s,%s,%s" % (
        identity.serial, identity.sensor, sf.fmt_number(identity.ug_per_lsb), sf.fmt_number(identity.t_lsb_per_c),
        sf.fmt_number(identity.t_lsb_at_25c), sf.fmt_number(identity.odr_hz)))


def sample_frames(t_us: np.ndarray, acc_counts: np.ndarray, temp_counts: np.ndarray) -> bytes:
    """Bridge `S` frames for n samples: (n,) uint32 board times, (n, 3) and (n,) raw counts."""
    acc = np.asarray(acc_counts, dtype=np.int64).tolist()
    tc = np.asarray(temp_counts, dtype=np.int64).tolist()
    parts = []
    for k, t in enumerate(np.asarray(t_us, dtype=np.int64).tolist()):
        a = acc[k]
        body = b"S,%d,%d,%d,%d,%d" % (t, a[0], a[1], a[2], tc[k])
        parts.append(b"$%s*%02X\n" % (body, sf.checksum(body)))
    return b"".join(parts)


def _unframe(line: bytes) -> str | None:
    """The body of one `$BODY*HH` line from the board, or None (bad checksum, not a frame)."""
    if len(line) < 4 or line[:1] != b"$" or line[-3:-2] != b"*":
        return None
    body = line[1:-3]
    try:
        ok = int(line[-2:], 16) == sf.checksum(body)
    except ValueError:
        return None
    return body.decode("ascii", "replace") if ok else None


class _Bridge:
    """The simulator's end of a sensor bridge: a non-blocking socket with an output queue, and the
    board's lines back (`$READY`, `$BOOT`, `$INIT`; others are skipped)."""

    def __init__(self, sock: socket.socket, on_line: Callable[[str], None] | None = None) -> None:
        self.sock = sock
        self.on_line = on_line
        sock.setblocking(False)
        # a small kernel buffer: a board that cannot keep up shows as a backlog here, which holds
        # the plant (SimStation backpressure) instead of hiding seconds of samples in the socket
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, BRIDGE_SNDBUF_BYTES)
        self._out = bytearray()
        self._rx = bytearray()
        self._loop = asyncio.get_running_loop()
        self._writer_on = False
        self.ready = asyncio.Event()
        self.closed = False
        self._loop.add_reader(sock.fileno(), self._on_readable)

    def _on_readable(self) -> None:
        try:
            data = self.sock.recv(4096)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            self.close()
            return
        self._rx += data
        while True:
            end = self._rx.find(b"\n")
            if end < 0:
                break
            line = bytes(self._rx[:end]).strip()
            del self._rx[: end + 1]
            start = line.rfind(b"$")  # bytes a reset cut off before the frame are skipped
            body = _unframe(line[start:]) if start >= 0 else None
            if body is None:
                continue
            if body == "READY":
                self.ready.set()
            if self.on_line is not None:
                self.on_line(body)
        del self._rx[:-256]

    def write(self, data: bytes) -> None:
        if self.closed:
            return
        if not self._out:
            try:
                n = self.sock.send(data)
            except BlockingIOError:
                n = 0
            except OSError:
                self.close()
                return
            data = data[n:]
            if not data:
                return
        self._out += data
        if not self._writer_on:
            self._loop.add_writer(self.sock.fileno(), self._on_writable)
            self._writer_on = True

    def _on_writable(self) -> None:
        try:
            n = self.sock.send(self._out)
        except BlockingIOError:
            return
        except OSError:
            self.close()
            return
        del self._out[:n]
        if not self._out:
            self._loop.remove_writer(self.sock.fileno())
            self._writer_on = False

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self._loop.remove_reader(self.sock.fileno())
        if self._writer_on:
            self._loop.remove_writer(self.sock.fileno())
        self.sock.close()


class FirmwareBoard:
    """One board running the C firmware (host process or QEMU), fed by the world (module doc).

    Serial boards expose `path` (the pty the station opens); CAN boards (host only) join a
    SimCanHub like SimCanBoard (`node_id`, `send`, `on_frame`). `power_cycle()` kills the board
    and starts it again on the same NVM; a QEMU board then has a new pty `path`.
    """

    def __init__(self, identity: Identity, kind: str = "host", *, node_id: int = 0, t0_us: int = 0,
                 workdir: str | Path | None = None) -> None:
        if kind not in KINDS:
            raise ValueError(f"firmware board kind must be one of {KINDS}, not {kind!r}")
        if kind == "qemu" and node_id:
            raise ValueError("the QEMU target is a serial board; CAN firmware boards run on the host target")
        self.identity = identity
        self.kind = kind
        self.node_id = int(node_id)
        self.t0_us = int(t0_us)
        self._tmp = tempfile.TemporaryDirectory(prefix=f"fw-{identity.serial}-") if workdir is None else None
        self.workdir = Path(workdir) if workdir is not None else Path(self._tmp.name)
        self.nvm_path = self.workdir / "nvm.bin"
        self.path = ""
        self.proc: subprocess.Popen | None = None
        self.bridge: _Bridge | None = None
        self.power_cycles = 0
        self.streaming = True  # the firmware decides; the world feeds its sensor all the time
        self.send = None  # CAN: set by SimCanHub.add
        self.on_stop = None  # replays only (drivers/sim/replay.py); not supported here
        self._master_fd = -1  # host serial/CAN: the device end of the station link
        self._slave_fd = -1  # kept open so the device end never sees a hang-up between openers
        self._can_rx = bytearray()
        self._can_link: socket.socket | None = None  # CAN: our end of the node's link
        self._can_fw_end: socket.socket | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._closed = False
        # recovery (issue 42): what the board said on the bridge, and the simulated sensor's fault
        self.boots_seen = 0  # `$BOOT` lines: starts of the firmware, resets included
        self.sensor_inits: list[float | None] = []  # sample clock (s) at each `$INIT` from the board
        self.sensor_held = False  # the sensor reset itself: no `$S` until the board's `$INIT`
        self.sensor_reset_at_s: float | None = None  # sample clock when it did
        self.samples_dropped = 0  # samples the held sensor could not deliver (lost for good)
        self.last_fed_s: float | None = None  # the sample clock: the newest sample the world made

    # ---- lifecycle --------------------------------------------------------------------------
    def start(self) -> None:
        """Create the station link (host) and launch the board; `wait_ready()` awaits its boot."""
        self._loop = asyncio.get_running_loop()
        if self.kind == "host" and self.node_id:
            self._can_link, self._can_fw_end = socket.socketpair()
            self._can_link.setblocking(False)
            self._loop.add_reader(self._can_link.fileno(), self._on_can_link)
            self._master_fd = self._can_fw_end.fileno()
        elif self.kind == "host":
            self._master_fd, self._slave_fd = os.openpty()
            tty.setraw(self._slave_fd)
            self.path = os.ttyname(self._slave_fd)
        self._launch()

    def _launch(self) -> None:
        need = missing_tools(self.kind) + ([] if self.kind == "host" or shutil.which("qemu-system-arm") else ["qemu-system-arm"])
        if need:
            raise RuntimeError(f"firmware-{self.kind} boards need {', '.join(need)} (Debian: gcc-arm-none-eabi "
                               "libnewlib-arm-none-eabi qemu-system-arm; scripts/test.sh installs them)")
        if self.kind == "host":
            binary = build("host") / "fwboard"
            ours, theirs = socket.socketpair()
            args = [str(binary), "--uart-fd", str(self._master_fd), "--bridge-fd", str(theirs.fileno()),
                    "--nvm", str(self.nvm_path)]
            if self.node_id:
                args += ["--can", str(self.node_id)]
            with open(self.workdir / "stderr.log", "ab") as log:
                self.proc = subprocess.Popen(args, pass_fds=(self._master_fd, theirs.fileno()), stdin=subprocess.DEVNULL,
                                             stdout=subprocess.DEVNULL, stderr=log)
            theirs.close()
            self.bridge = _Bridge(ours, self._on_bridge_line)
        else:
            elf = build("qemu") / "fw.elf"
            sock_path = self.workdir / "bridge.sock"
            if sock_path.exists():
                sock_path.unlink()
            listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            listener.bind(str(sock_path))
            listener.listen(1)
            self._listener = listener
            self.proc = subprocess.Popen(
                ["qemu-system-arm", "-M", "netduinoplus2", "-display", "none", "-monitor", "none",
                 "-kernel", str(elf), "-serial", "pty", "-serial", "chardev:br",
                 "-chardev", f"socket,id=br,path={sock_path}",
                 "-semihosting-config", "enable=on,target=native"],
                cwd=self.workdir, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
            self.bridge = None
        if self.bridge is not None:
            self.bridge.write(strap_frame(self.identity))

    async def wait_ready(self, timeout_s: float = BOOT_TIMEOUT_S) -> None:
        """Return once the board has booted (its `$READY` on the bridge); raise if it does not."""
        if self.kind == "qemu":
            await asyncio.wait_for(self._qemu_attach(), timeout_s)
        assert self.bridge is not None
        loop = asyncio.get_running_loop()
        end = loop.time() + timeout_s
        try:
            # The strap again until the board answers: a QEMU board's USART drops what arrives
            # before the guest enabled it (the socket connects first); the firmware takes the first
            while True:
                try:
                    await asyncio.wait_for(self.bridge.ready.wait(), min(0.25, max(0.0, end - loop.time())))
                    break
                except asyncio.TimeoutError:
                    if loop.time() >= end or self.bridge.closed:
                        raise
                    self.bridge.write(strap_frame(self.identity))
        except asyncio.TimeoutError:
            raise RuntimeError(f"firmware board {self.identity.serial} ({self.kind}) did not boot in {timeout_s:g} s; "
                               f"see {self.workdir}") from None

    async def _qemu_attach(self) -> None:
        """Read QEMU's pty path, hold the pty open, accept its bridge connection, send the strap."""
        assert self.proc is not None and self.proc.stdout is not None
        out = self.proc.stdout
        line = b""
        while True:
            line = await asyncio.to_thread(out.readline)
            if not line:
                raise RuntimeError(f"qemu exited before opening its serial pty (exit {self.proc.poll()})")
            m = QEMU_PTY_RE.search(line)
            if m:
                break
        self.path = m.group(1).decode()
        if self._slave_fd >= 0:
            os.close(self._slave_fd)
        # QEMU discards what its pty writes while no one holds the other end: hold it from now on
        self._slave_fd = os.open(self.path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(self._slave_fd)
        self._listener.setblocking(False)
        conn, _ = await self._loop.sock_accept(self._listener)
        self._listener.close()
        self.bridge = _Bridge(conn, self._on_bridge_line)
        self.bridge.write(strap_frame(self.identity))
        # QEMU's own messages go to a log file, read by a thread of its own (not the loop's
        # executor, which the daemon needs and which N boards would fill for their lifetime)
        threading.Thread(target=self._drain_qemu_output, name=f"qemu-log-{self.identity.serial}", daemon=True).start()

    def _drain_qemu_output(self) -> None:
        proc = self.proc
        if proc is not None and proc.stdout is not None:
            with open(self.workdir / "qemu.log", "ab") as log:
                for line in proc.stdout:
                    log.write(line)

    def _kill(self) -> None:
        if self.bridge is not None:
            self.bridge.close()
            self.bridge = None
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(timeout=10)
        self.proc = None

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._kill()
        if self._can_link is not None and self._loop is not None:
            self._loop.remove_reader(self._can_link.fileno())
            self._can_link.close()
            self._can_link = None
        if self._can_fw_end is not None:
            self._can_fw_end.close()
            self._can_fw_end, self._master_fd = None, -1
        for fd in (self._master_fd, self._slave_fd):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master_fd = self._slave_fd = -1
        if self._tmp is not None:
            self._tmp.cleanup()

    @property
    def connected(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def power_cycle(self) -> None:
        """Power lost (SIGKILL: whatever it was doing) and back: RAM gone, NVM file kept.
        Await `wait_ready()` afterwards; a QEMU board's `path` is new once it is ready."""
        self._kill()
        self.power_cycles += 1
        self.sensor_held = False  # the sensor loses power too: it starts afresh with the board
        self._launch()

    def backlog_bytes(self, now: float) -> int:
        """Sensor bytes the board has not taken yet (SimStation holds the plant while it is large:
        an emulated board on a loaded machine falls behind the world, not out of step with it)."""
        b = self.bridge
        return len(b._out) if b is not None and not b.closed and self.connected else 0

    # ---- the board's lines on the bridge, and fault injection (issue 42) ------------------------
    def _on_bridge_line(self, body: str) -> None:
        if body == "BOOT":
            # the firmware (re)started: it may have kept its identity (answers `$READY` again) or
            # not (then this strap boots it); either way the simulator does not restart anything
            self.boots_seen += 1
            if self.bridge is not None:
                self.bridge.write(strap_frame(self.identity))
        elif body == "INIT":
            self.sensor_inits.append(self.last_fed_s)
            self.sensor_held = False

    def sensor_reset(self) -> None:
        """The simulated sensor resets itself (a supply glitch): it stops sending samples until the
        board re-initialises it (`$INIT`); its clock runs on, the samples meanwhile are lost."""
        self.sensor_held = True
        self.sensor_reset_at_s = self.last_fed_s

    def inject(self, fault: str) -> None:
        """`$X,<fault>` on the bridge: "hardfault" (an undefined instruction) or "hang" (the main
        loop stops: the watchdog must reset the board)."""
        if fault not in ("hardfault", "hang"):
            raise ValueError(f"unknown fault {fault!r}; selfcal_skew has its own method")
        self._bridge_send(sf.encode(f"X,{fault}"))

    def selfcal_skew(self, tdb_mg_per_c: float) -> None:
        """`$X,selfcal_skew,<mg_per_c>`: the board's on-board calibrator's TDB is off by this much."""
        self._bridge_send(sf.encode(f"X,selfcal_skew,{sf.fmt_number(float(tdb_mg_per_c))}"))

    def _bridge_send(self, frame: bytes) -> None:
        if self.bridge is None or self.bridge.closed:
            raise RuntimeError(f"firmware board {self.identity.serial} has no bridge (not started?)")
        self.bridge.write(frame)

    # ---- the sensor: samples from the world ---------------------------------------------------
    def feed(self, time_s: np.ndarray, acc_counts: np.ndarray, temp_counts: np.ndarray) -> None:
        """What the board's sensor measured; the firmware decides what (if anything) to send."""
        if len(time_s) == 0:
            return
        self.last_fed_s = float(time_s[-1])
        if self.sensor_held:
            self.samples_dropped += len(time_s)
            return
        if self.bridge is None or not self.bridge.ready.is_set():
            return
        t_us = (np.round(np.asarray(time_s) * 1e6).astype(np.int64) + self.t0_us) & 0xFFFFFFFF
        self.bridge.write(sample_frames(t_us, acc_counts, temp_counts))

    # ---- CAN: the node's link carries slcan-style lines ----------------------------------------
    def on_frame(self, arb_id: int, data: bytes) -> None:
        """A frame on the bus (from the host): pass it to the node like its CAN controller would."""
        if self._can_link is None or not self.connected:
            return
        line = b"t%03X%d%s\r" % (arb_id, len(data), data.hex().upper().encode())
        try:
            self._can_link.send(line)
        except OSError:  # a full link is a full CAN controller: the frame is lost, as on a bus
            pass

    def _on_can_link(self) -> None:
        assert self._can_link is not None
        try:
            data = self._can_link.recv(65536)
        except (BlockingIOError, OSError):
            return
        self._can_rx += data
        while True:
            end = self._can_rx.find(b"\r")
            if end < 0:
                break
            line = bytes(self._can_rx[:end]).strip()
            del self._can_rx[: end + 1]
            if len(line) >= 5 and line[:1] == b"t":
                try:
                    arb, dlc = int(line[1:4], 16), int(line[4:5])
                    payload = bytes.fromhex(line[5 : 5 + 2 * dlc].decode())
                except ValueError:
                    continue
                if self.send is not None:
                    self.send(arb, payload)


BOARD_SPECS = ("python", "firmware-host", "firmware-qemu", "firmware-host-can")


def plan_firmware(specs: list[str], n_serial: int, n_can: int) -> dict[int, str]:
    """DUT index -> firmware kind from `--boards KIND[:N]` specs, filled in order.

    `firmware-host` / `firmware-qemu` take the next N serial slots (default 2), `firmware-host-can`
    the next N CAN nodes, `python` N serial slots of the Python board model (the default for any
    slot not named). Raises ValueError with the reason when the specs do not fit the boards.
    """
    plan: dict[int, str] = {}
    next_serial, next_can = 0, 0
    for spec in specs:
        kind, _, count = spec.partition(":")
        if kind not in BOARD_SPECS:
            raise ValueError(f"unknown board kind {kind!r}; known: {', '.join(BOARD_SPECS)}")
        try:
            n = int(count) if count else 2
        except ValueError:
            raise ValueError(f"board count in {spec!r} is not a number") from None
        if n < 0:
            raise ValueError(f"board count in {spec!r} is negative")
        if kind == "firmware-host-can":
            if next_can + n > n_can:
                raise ValueError(f"{spec}: only {n_can} CAN boards (--can)")
            plan.update({n_serial + next_can + k: "host" for k in range(n)})
            next_can += n
            continue
        if next_serial + n > n_serial:
            raise ValueError(f"{spec}: only {n_serial} serial boards (--serial)")
        if kind != "python":
            plan.update({next_serial + k: kind.removeprefix("firmware-") for k in range(n)})
        next_serial += n
    return plan
