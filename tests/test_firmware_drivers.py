"""Sensor drivers of the board firmware (firmware/drivers/lis3dsh.c, adxl355.c) on the host.

The drivers are compiled with `cc` into a temporary shared library together with a two-line
harness (the SPI address helpers are static inline), and driven through ctypes against a fake SPI
register model written in Python: every register access of the driver goes through the model's
read/write callbacks, so the tests see exactly which registers init writes and what a burst reads.
"""

from __future__ import annotations

import ctypes
import os
import shutil
import subprocess
from pathlib import Path

import pytest

FIRMWARE = Path(__file__).resolve().parents[1] / "firmware"

HARNESS = r"""
#include "lis3dsh.h"
#include "adxl355.h"
uint8_t h_lis3dsh_spi_addr(uint8_t reg, int rd) { return lis3dsh_spi_addr(reg, rd); }
uint8_t h_adxl355_spi_addr(uint8_t reg, int rd) { return adxl355_spi_addr(reg, rd); }
"""

READ_FN = ctypes.CFUNCTYPE(ctypes.c_int32, ctypes.c_void_p, ctypes.c_uint8, ctypes.POINTER(ctypes.c_uint8), ctypes.c_uint16)
WRITE_FN = ctypes.CFUNCTYPE(ctypes.c_int32, ctypes.c_void_p, ctypes.c_uint8, ctypes.POINTER(ctypes.c_uint8), ctypes.c_uint16)


class Ctx(ctypes.Structure):
    _fields_ = [("read", READ_FN), ("write", WRITE_FN), ("handle", ctypes.c_void_p)]


class RawSample(ctypes.Structure):
    _fields_ = [("t_us", ctypes.c_uint32), ("acc", ctypes.c_int32 * 3), ("temp", ctypes.c_int32)]


@pytest.fixture(scope="module")
def lib(tmp_path_factory):
    cc = shutil.which("cc")
    if cc is None:
        if os.environ.get("STATION_REQUIRE_FIRMWARE") == "1":
            pytest.fail("cc not found and STATION_REQUIRE_FIRMWARE=1")
        pytest.skip("no host C compiler (cc)")
    d = tmp_path_factory.mktemp("drivers")
    (d / "harness.c").write_text(HARNESS)
    so = d / "libdrivers.so"
    cmd = [cc, "-shared", "-fPIC", "-O1", "-std=c99", "-Wall", "-Wextra", "-Werror", "-Wshadow",
           f"-I{FIRMWARE / 'core'}", f"-I{FIRMWARE / 'drivers'}",
           str(FIRMWARE / "drivers" / "lis3dsh.c"), str(FIRMWARE / "drivers" / "adxl355.c"), str(d / "harness.c"),
           "-o", str(so)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    lib = ctypes.CDLL(str(so))
    for name in ("lis3dsh_init", "lis3dsh_data_ready", "lis3dsh_read_sample", "lis3dsh_who_am_i",
                 "lis3dsh_fifo_stream", "lis3dsh_fifo_status", "lis3dsh_fifo_read",
                 "adxl355_init", "adxl355_data_ready", "adxl355_read_sample"):
        getattr(lib, name).restype = ctypes.c_int32
    lib.lis3dsh_fifo_t_us.restype = ctypes.c_uint32
    lib.lis3dsh_fifo_t_us.argtypes = [ctypes.c_uint32] * 4
    lib.lis3dsh_temp_c.restype = ctypes.c_float
    lib.lis3dsh_temp_c.argtypes = [ctypes.c_int32]
    lib.adxl355_temp_c.restype = ctypes.c_float
    lib.adxl355_temp_c.argtypes = [ctypes.c_int32]
    lib.lis3dsh_odr_hz.restype = ctypes.c_float
    lib.adxl355_decode_axis.restype = ctypes.c_int32
    lib.adxl355_decode_temp.restype = ctypes.c_int32
    lib.h_lis3dsh_spi_addr.restype = ctypes.c_uint8
    lib.h_adxl355_spi_addr.restype = ctypes.c_uint8
    return lib


class FakeSpi:
    """Register file behind the driver's read/write callbacks; logs every access."""

    def __init__(self, regs: dict[int, int], auto_inc=lambda regs: True, on_write=None):
        self.regs = bytearray(256)
        for k, v in regs.items():
            self.regs[k] = v
        self.auto_inc = auto_inc
        self.on_write = on_write
        self.writes: list[tuple[int, int]] = []
        self.reads: list[tuple[int, int]] = []
        self.fail = False
        self._read = READ_FN(self.read)
        self._write = WRITE_FN(self.write)
        self.ctx = Ctx(self._read, self._write, None)

    def read(self, handle, reg, buf, n):
        if self.fail:
            return -1
        self.reads.append((reg, n))
        inc = self.auto_inc(self.regs)
        for i in range(n):
            buf[i] = self.regs[(reg + i) & 0xFF if inc else reg]
        return 0

    def write(self, handle, reg, buf, n):
        if self.fail:
            return -1
        for i in range(n):
            self.writes.append((reg + i, buf[i]))
            self.regs[reg + i] = buf[i]
            if self.on_write:
                self.on_write(self, reg + i, buf[i])
        return 0


# ---- LIS3DSH ------------------------------------------------------------------------------

def lis_model(who=0x3F) -> FakeSpi:
    # multi-byte SPI reads auto-increment only with CTRL_REG6.ADD_INC (bit 4)
    return FakeSpi({0x0F: who}, auto_inc=lambda r: bool(r[0x25] & 0x10))


def test_spi_address_bytes(lib):
    assert lib.h_lis3dsh_spi_addr(0x0F, 1) == 0x8F
    assert lib.h_lis3dsh_spi_addr(0x20, 0) == 0x20
    assert lib.h_adxl355_spi_addr(0x00, 1) == 0x01
    assert lib.h_adxl355_spi_addr(0x2D, 0) == 0x5A
    assert lib.h_adxl355_spi_addr(0x08, 1) == 0x11


def test_lis3dsh_init_writes_the_right_registers(lib):
    spi = lis_model()
    assert lib.lis3dsh_init(ctypes.byref(spi.ctx), 6, 0) == 0   # 100 Hz, +-2 g
    assert spi.writes == [
        (0x25, 0x10),   # CTRL_REG6: ADD_INC
        (0x24, 0x00),   # CTRL_REG5: +-2 g, 4-wire SPI
        (0x20, 0x6F),   # CTRL_REG4: ODR 100 Hz, BDU, X/Y/Z on
        (0x23, 0xC8),   # CTRL_REG3: DR_EN, active high, INT1
    ]
    assert lib.lis3dsh_odr_hz(6) == 100.0


def test_lis3dsh_wrong_who_am_i_fails_init(lib):
    spi = lis_model(who=0x33)   # a LIS3DH answers 0x33
    assert lib.lis3dsh_init(ctypes.byref(spi.ctx), 6, 0) == -2
    assert spi.writes == []
    spi = lis_model()
    spi.fail = True
    assert lib.lis3dsh_init(ctypes.byref(spi.ctx), 6, 0) == -1
    assert lib.lis3dsh_init(ctypes.byref(lis_model().ctx), 12, 0) == -3   # no such ODR code


def test_lis3dsh_sample_sign_extension_and_temperature(lib):
    spi = lis_model()
    assert lib.lis3dsh_init(ctypes.byref(spi.ctx), 6, 0) == 0
    assert lib.lis3dsh_data_ready(ctypes.byref(spi.ctx)) == 0
    spi.regs[0x27] = 0x0F   # ZYXDA
    assert lib.lis3dsh_data_ready(ctypes.byref(spi.ctx)) == 1
    for i, v in enumerate((-2, 32767, -32768)):
        spi.regs[0x28 + 2 * i: 0x2A + 2 * i] = (v & 0xFFFF).to_bytes(2, "little")
    spi.regs[0x0C] = 0xF6   # -10 -> 15 C
    s = RawSample()
    assert lib.lis3dsh_read_sample(ctypes.byref(spi.ctx), ctypes.byref(s)) == 0
    assert list(s.acc) == [-2, 32767, -32768]
    assert s.temp == -10
    assert lib.lis3dsh_temp_c(s.temp) == pytest.approx(15.0)
    assert lib.lis3dsh_temp_c(0) == pytest.approx(25.0)
    assert (0x28, 6) in spi.reads   # one burst X_L..Z_H


def test_lis3dsh_burst_needs_add_inc(lib):
    """Without init the part does not auto-increment: the burst reads OUT_X_L six times."""
    spi = lis_model()
    spi.regs[0x28:0x2E] = bytes([1, 2, 3, 4, 5, 6])
    s = RawSample()
    assert lib.lis3dsh_read_sample(ctypes.byref(spi.ctx), ctypes.byref(s)) == 0
    assert list(s.acc) == [0x0101] * 3
    assert lib.lis3dsh_init(ctypes.byref(spi.ctx), 6, 0) == 0
    assert lib.lis3dsh_read_sample(ctypes.byref(spi.ctx), ctypes.byref(s)) == 0
    assert list(s.acc) == [0x0201, 0x0403, 0x0605]


class LisFifo(FakeSpi):
    """A LIS3DSH with its 32-level FIFO: samples pushed by the test; a 6-byte burst from OUT_X_L
    pops the oldest one (what the part does in FIFO mode); FIFO_SRC reports the level, WTM, EMPTY."""

    def __init__(self) -> None:
        super().__init__({0x0F: 0x3F}, auto_inc=lambda r: bool(r[0x25] & 0x10))
        self.fifo: list[tuple[int, int, int]] = []
        self.overrun = False

    def push(self, xyz) -> None:
        self.fifo.append(tuple(xyz))
        if len(self.fifo) > 32:   # stream mode: the oldest is overwritten
            self.fifo.pop(0)
            self.overrun = True

    def read(self, handle, reg, buf, n):
        if self.fail:
            return -1
        self.reads.append((reg, n))
        if reg == 0x2F:
            wtm = self.regs[0x2E] & 0x1F
            level = len(self.fifo)
            v = (level & 0x1F) | (0x20 if level == 0 else 0) | (0x40 if self.overrun else 0) | (0x80 if level >= wtm else 0)
            buf[0] = v
            return 0
        if reg == 0x28 and n == 6 and self.fifo:
            raw = b"".join(int(v & 0xFFFF).to_bytes(2, "little") for v in self.fifo.pop(0))
            for i in range(6):
                buf[i] = raw[i]
            return 0
        return super().read(handle, reg, buf, n)


def test_lis3dsh_fifo_stream_mode_registers(lib):
    spi = LisFifo()
    assert lib.lis3dsh_init(ctypes.byref(spi.ctx), 6, 0) == 0
    spi.writes.clear()
    assert lib.lis3dsh_fifo_stream(ctypes.byref(spi.ctx), 10) == 0
    assert spi.writes == [
        (0x2E, 0x00),   # FIFO_CTRL: bypass first (empties the FIFO)
        (0x25, 0x74),   # CTRL_REG6: FIFO_EN, WTM_EN, ADD_INC, P1_WTM (watermark on INT1)
        (0x2E, 0x4A),   # FIFO_CTRL: stream mode (010), watermark 10
        (0x23, 0x48),   # CTRL_REG3: INT1 on, active high; data-ready NOT routed
    ]
    assert lib.lis3dsh_fifo_stream(ctypes.byref(spi.ctx), 0) == -3
    assert lib.lis3dsh_fifo_stream(ctypes.byref(spi.ctx), 32) == -3


def test_lis3dsh_fifo_status_and_read_oldest_first(lib):
    spi = LisFifo()
    assert lib.lis3dsh_init(ctypes.byref(spi.ctx), 6, 0) == 0
    assert lib.lis3dsh_fifo_stream(ctypes.byref(spi.ctx), 10) == 0
    count, src = ctypes.c_uint32(99), ctypes.c_uint8()
    assert lib.lis3dsh_fifo_status(ctypes.byref(spi.ctx), ctypes.byref(count), ctypes.byref(src)) == 0
    assert count.value == 0 and src.value & 0x20   # EMPTY
    pushed = [(i, -2 * i, 1000 + i) for i in range(12)]
    for xyz in pushed:
        spi.push(xyz)
    spi.regs[0x0C] = 0xFB   # OUT_T -5 -> 20 C
    assert lib.lis3dsh_fifo_status(ctypes.byref(spi.ctx), ctypes.byref(count), ctypes.byref(src)) == 0
    assert count.value == 12 and src.value & 0x80 and not src.value & 0x40
    out = (RawSample * 32)()
    assert lib.lis3dsh_fifo_read(ctypes.byref(spi.ctx), out, 12) == 0
    assert [tuple(out[k].acc) for k in range(12)] == pushed
    assert {out[k].temp for k in range(12)} == {-5}
    assert spi.fifo == []
    # a full FIFO: FSS has 5 bits, 32 stored reads as 0 with EMPTY clear
    for i in range(40):
        spi.push((i, 0, 0))
    assert lib.lis3dsh_fifo_status(ctypes.byref(spi.ctx), ctypes.byref(count), ctypes.byref(src)) == 0
    assert count.value == 32 and src.value & 0x40   # OVRN: 8 samples were overwritten
    assert lib.lis3dsh_fifo_read(ctypes.byref(spi.ctx), out, 32) == 0
    assert [out[k].acc[0] for k in range(32)] == list(range(8, 40))
    assert lib.lis3dsh_fifo_read(ctypes.byref(spi.ctx), out, 33) == -3


def test_lis3dsh_fifo_sample_times_from_the_watermark(lib):
    # watermark 10 at 100 Hz: the edge is the 10th sample's data-ready; the others 10 ms apart
    t_wtm, p = 5_000_000, 10_000
    got = [lib.lis3dsh_fifo_t_us(t_wtm, 10, k, p) for k in range(12)]
    assert got == [t_wtm + (k - 9) * p for k in range(12)]
    # across the uint32 wrap of the board clock
    assert lib.lis3dsh_fifo_t_us(20_000, 10, 0, p) == (20_000 - 9 * p) % 2**32
    assert lib.lis3dsh_fifo_t_us(2**32 - 5_000, 10, 11, p) == (2**32 - 5_000 + 2 * p) % 2**32


def test_bus_errors_reach_the_caller(lib):
    """A platform read/write that fails (an SPI timeout on the board) is an error at every level."""
    spi = LisFifo()
    assert lib.lis3dsh_init(ctypes.byref(spi.ctx), 6, 0) == 0
    spi.push((1, 2, 3))
    spi.fail = True
    count = ctypes.c_uint32()
    out = (RawSample * 32)()
    assert lib.lis3dsh_fifo_stream(ctypes.byref(spi.ctx), 10) == -1
    assert lib.lis3dsh_fifo_status(ctypes.byref(spi.ctx), ctypes.byref(count), None) == -1
    assert lib.lis3dsh_fifo_read(ctypes.byref(spi.ctx), out, 1) == -1
    assert lib.lis3dsh_read_sample(ctypes.byref(spi.ctx), ctypes.byref(RawSample())) == -1
    assert lib.lis3dsh_data_ready(ctypes.byref(spi.ctx)) == -1
    adxl = adxl_model()
    assert lib.adxl355_init(ctypes.byref(adxl.ctx), 5, 1) == 0
    adxl.fail = True
    assert lib.adxl355_read_sample(ctypes.byref(adxl.ctx), ctypes.byref(RawSample())) == -1
    assert lib.adxl355_data_ready(ctypes.byref(adxl.ctx)) == -1


# ---- ADXL355 ------------------------------------------------------------------------------

ADXL_RESET = {0x28: 0x00, 0x2C: 0x81, 0x2D: 0x01}


def adxl_model(part=0xED) -> FakeSpi:
    def on_write(spi, reg, val):
        if reg == 0x2F and val == 0x52:   # soft reset: registers back to their reset values
            for k, v in ADXL_RESET.items():
                spi.regs[k] = v
    regs = {0x00: 0xAD, 0x01: 0x1D, 0x02: part, 0x03: 0x01, **ADXL_RESET}
    return FakeSpi(regs, on_write=on_write)


def encode20(v: int) -> bytes:
    u = (v & 0xFFFFF) << 4   # left-justified in 24 bits
    return u.to_bytes(3, "big")


def test_adxl355_init_writes_the_right_registers(lib):
    spi = adxl_model()
    spi.regs[0x2C] = 0x83   # something else before the reset
    assert lib.adxl355_init(ctypes.byref(spi.ctx), 5, 1) == 0   # 125 Hz, +-2 g
    assert spi.writes == [(0x2F, 0x52), (0x28, 0x05), (0x2C, 0x81), (0x2D, 0x00)]
    assert spi.reads[0] == (0x00, 3)   # DEVID_AD, DEVID_MST, PARTID in one burst


def test_adxl355_wrong_id_fails_init(lib):
    spi = adxl_model(part=0xEC)
    assert lib.adxl355_init(ctypes.byref(spi.ctx), 5, 1) == -2
    assert spi.writes == []
    assert lib.adxl355_init(ctypes.byref(adxl_model().ctx), 5, 0) == -3   # no range code 0


@pytest.mark.parametrize("v", [0, 1, -1, 0x7FFFF, -0x80000, 256000, -256000, 12345, -54321])
def test_adxl355_20bit_sign_extension(lib, v):
    b = (ctypes.c_uint8 * 3)(*encode20(v))
    assert lib.adxl355_decode_axis(b) == v


def test_adxl355_sample_and_temperature(lib):
    spi = adxl_model()
    assert lib.adxl355_init(ctypes.byref(spi.ctx), 5, 1) == 0
    assert lib.adxl355_data_ready(ctypes.byref(spi.ctx)) == 0
    spi.regs[0x04] = 0x01
    assert lib.adxl355_data_ready(ctypes.byref(spi.ctx)) == 1
    acc = (-1, 255999, -524288)
    spi.regs[0x06] = 0xF7   # upper nibble is not temperature
    spi.regs[0x07] = 0x5D   # 0x75D = 1885
    for i, v in enumerate(acc):
        spi.regs[0x08 + 3 * i: 0x0B + 3 * i] = encode20(v)
    spi.regs[0x0A] |= 0x0F   # reserved low bits of XDATA1 must be ignored
    s = RawSample()
    assert lib.adxl355_read_sample(ctypes.byref(spi.ctx), ctypes.byref(s)) == 0
    assert list(s.acc) == list(acc)
    assert s.temp == 1885
    assert (0x06, 11) in spi.reads   # one burst TEMP2..ZDATA1
    assert lib.adxl355_temp_c(1885) == pytest.approx(25.0)
    assert lib.adxl355_temp_c(1885 - 181) == pytest.approx(45.0, abs=1e-4)   # -9.05 LSB/C
    assert lib.adxl355_decode_temp(0x0F, 0xFF) == 4095
