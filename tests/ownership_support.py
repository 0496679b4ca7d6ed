"""The fault matrix's "second station --check mid-batch" injection (issue 36, part 4).

`check_during_batch(ctx)` is a fault-matrix `inject` (tests/fault_matrix_support.py `Plan.inject`):
at the fast-thermal P hot step (step 1, lamp on) it writes the running station's config to a TOML
file and runs `station serve --check --config THAT` as a real subprocess. The in-process Station
holds the claim on its database, ports and relay (station/daemon/ownership.py, taken in
`Station.start()`), so the check must exit non-zero with this process's PID in its one stderr line,
and, while the plant is held at that moment, send no byte to a board and no Modbus write. That it
harmed nothing else (no DUT faulted, no interrupted batch, the lamp not switched off under the
batch) is the matrix's own "unharmed" expectation on the batch's DUTs.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Protocol

ROOT = Path(__file__).resolve().parents[1]
# Wall seconds the plant is held while the check runs (well under the 10 s stall timeout); a check
# slower than that (a loaded machine) is awaited after the hold, its refusal still checked.
HOLD_S = 4.0
CHECK_TIMEOUT_S = 60.0

TomlValue = str | int | float | bool | list["TomlValue"] | dict[str, "TomlValue"] | None


class _Board(Protocol):
    commands: list[bytes]


class _Modbus(Protocol):
    writes: list[tuple[int, int, int, object]]


class _Sim(Protocol):
    serial_boards: list[_Board]
    can_boards: list[_Board]
    modbus: _Modbus | None


class _Config(Protocol):
    def model_dump(self, *, mode: str, exclude_none: bool) -> dict[str, TomlValue]: ...


class _Station(Protocol):
    config: _Config


class _Ctx(Protocol):
    sim: _Sim
    st: _Station

    def at_step(self, index: int, min_samples: int = 0,
                timeout_s: float = 120.0) -> contextlib.AbstractAsyncContextManager[None]: ...


def toml_value(v: TomlValue) -> str:
    """One TOML value: inline tables and arrays nest, so any config dict is one line per key."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a JSON string is a TOML basic string
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v if x is not None) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(k)} = {toml_value(x)}" for k, x in v.items() if x is not None) + "}"
    raise TypeError(f"no TOML for {v!r}")


def config_toml(config: _Config) -> str:
    data = config.model_dump(mode="json", exclude_none=True)
    return "".join(f"{json.dumps(k)} = {toml_value(v)}\n" for k, v in data.items())


async def check_during_batch(ctx: _Ctx) -> None:
    """Inject: `station serve --check` on the running station's config at P hot; AssertionError
    unless it is refused (non-zero, one stderr line with our PID and host) and touched no board
    and no Modbus device while the plant was held."""
    import socket

    with tempfile.TemporaryDirectory(prefix="ownership-check-") as tmp:
        toml = Path(tmp) / "station.toml"
        toml.write_text(config_toml(ctx.st.config))
        boards = [*ctx.sim.serial_boards, *ctx.sim.can_boards]
        env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
        async with ctx.at_step(1, 10):
            sent = [len(b.commands) for b in boards]
            writes = len(ctx.sim.modbus.writes) if ctx.sim.modbus is not None else 0
            t0 = time.monotonic()
            proc = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "cli", "serve", "--config", str(toml), "--check", cwd=ROOT, env=env,
                stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
            talk = asyncio.ensure_future(proc.communicate())
            done, _ = await asyncio.wait({talk}, timeout=HOLD_S)
            if done:
                await asyncio.sleep(0.1)  # anything in flight lands while the plant still holds
                new_cmds = {i: b.commands[n:] for i, (b, n) in enumerate(zip(boards, sent)) if b.commands[n:]}
                new_writes = ctx.sim.modbus.writes[writes:] if ctx.sim.modbus is not None else []
                if new_cmds or new_writes:
                    raise AssertionError(f"serve --check touched the hardware of a running station: "
                                         f"board commands {new_cmds}, Modbus writes {new_writes}")
        try:
            out, err = await asyncio.wait_for(talk, CHECK_TIMEOUT_S)
        except asyncio.TimeoutError:
            proc.kill()
            await proc.wait()
            raise AssertionError(f"serve --check did not end within {CHECK_TIMEOUT_S:g} s") from None
        took_s = time.monotonic() - t0
        lines = [ln for ln in err.decode().splitlines() if ln.strip()]
        if (proc.returncode == 0 or len(lines) != 1 or f"PID {os.getpid()} on host {socket.gethostname()}" not in lines[0]
                or "held by" not in lines[0]):
            raise AssertionError(f"serve --check on a running station's config was not refused with its owner "
                                 f"(exit {proc.returncode} after {took_s:.1f} s): stdout {out.decode()!r}, "
                                 f"stderr {err.decode()!r}")
