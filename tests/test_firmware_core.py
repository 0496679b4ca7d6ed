"""The board firmware's portable C core (firmware/core) against the station's own Python codecs.

ctypes on build/host/libfwcore.so. Every check compares the C result with an independent Python
implementation the station already trusts (zlib, drivers/protocol/*, drivers/sim/board_nvm.py),
both ways, on shared random vectors: a wrong CRC polynomial, a flipped TDB sign, a lower-case
checksum or a mis-rounded float fails here. A fake HAL (ctypes callbacks: UART bytes, CAN frames, two
NVM slots as bytearrays with write faults) drives fw_board_init / fw_uart_rx / fw_can_rx / fw_sample.
"""

from __future__ import annotations

import ctypes as C
import random
import struct
import zlib

import numpy as np
import pytest

from contracts.board_health import BoardRecordInfo
from contracts.types import Identity
from drivers.protocol import can_frames as cf
from drivers.protocol import serial_frames as sf
from drivers.protocol.cal_record import crc32_f32, to_f32
from drivers.sim.board_nvm import CalFirmware
from drivers.sim.firmware_build import build, missing_tools
from drivers.sim.slcan_pty import can_scale
from tests.firmware_ctypes import header_define
from tests.firmware_ctypes import CAN_FN, FwHal, FwIdentity, FwRawSample, NVM_RD, NVM_WR, UART_FN
from tests.firmware_nvm import decode_slot, encode_record, slot_image
from tests.firmware_proc import split_keys

LIS = Identity("SN0001", "LIS3DSH", "fw-c-1.0", 60.0, 1.0, 0.0, 3.125)
ADXL = Identity("AX0001", "ADXL355", "fw-c-1.0", 3.9, -9.05, 1885.0, 3.125)


SLOT = header_define("fw_hal.h", "FW_NVM_SLOT_BYTES")  # 512 since the version-2 record
RX_LINE_MAX = header_define("fw_board.h", "FW_RX_LINE_MAX")
TX_BODY_MAX = header_define("fw_frame.h", "FW_TX_BODY_MAX")
REPLY_STEP = header_define("fw_board.h", "FW_REPLY_STEP_VALUES")
NO_LAYOUT = 0xFFFFFFFF  # fw_layout of a name it does not know


class FwCal(C.Structure):
    _fields_ = [("thermal", C.c_float * 6), ("sfem", C.c_float * 12), ("thermal_crc", C.c_uint32),
                ("sfem_crc", C.c_uint32), ("has_sfem", C.c_uint8), ("comp", C.c_uint8)]


class FwBoardHead(C.Structure):
    """fw_board_t up to selfcal_on (the fields before the calibrator's state never move)."""
    _fields_ = [("hal", C.c_void_p), ("id", FwIdentity), ("can_node", C.c_uint8), ("cal", FwCal),
                ("nvm_status", C.c_int), ("nvm_seq", C.c_uint32), ("streaming", C.c_uint8),
                ("seq", C.c_uint32), ("decim", C.c_uint32), ("phase", C.c_uint32), ("odr_hz", C.c_float),
                ("can_cal_have", C.c_uint8), ("can_cal_fields", C.c_float * 6), ("rx_line", C.c_uint8 * RX_LINE_MAX),
                ("rx_len", C.c_uint32), ("rx_overflow", C.c_uint8), ("rx_bad_frames", C.c_uint32),
                ("selfcal_on", C.c_uint8)]


class FwTx(C.Structure):
    """fw_tx_t of fw_frame.h."""
    _fields_ = [("body", C.c_char * TX_BODY_MAX), ("len", C.c_uint32), ("overflow", C.c_uint8)]


MIRRORS = {"fw_identity_t": FwIdentity, "fw_cal_t": FwCal, "fw_hal_t": FwHal, "fw_raw_sample_t": FwRawSample,
           "fw_tx_t": FwTx}


def layout_mismatches(so, mirrors: dict | None = None) -> list[str]:
    """Every way the ctypes mirrors differ from the compiler's layout (fw_layout): whole sizes,
    every field offset, and FwBoardHead's offsets inside fw_board_t (a prefix: its size is not)."""
    so.fw_layout.argtypes = [C.c_char_p]
    so.fw_layout.restype = C.c_uint32
    bad = []
    for cname, mirror in [*(mirrors or MIRRORS).items(), ("fw_board_t", FwBoardHead)]:
        if cname != "fw_board_t" and C.sizeof(mirror) != so.fw_layout(cname.encode()):
            bad.append(f"sizeof {cname}: C {so.fw_layout(cname.encode())}, mirror {C.sizeof(mirror)}")
        for fname, _ in mirror._fields_:
            off = so.fw_layout(f"{cname}.{fname}".encode())
            if cname in ("fw_hal_t", "fw_raw_sample_t") and off == NO_LAYOUT:
                continue  # fw_hal.h's structs: sizes only (their fields are the HAL contract, not exported)
            if off != getattr(mirror, fname).offset:
                bad.append(f"{cname}.{fname}: C offset {off}, mirror {getattr(mirror, fname).offset}")
    return bad


@pytest.fixture(scope="module")
def lib():
    if missing_tools("host"):
        pytest.skip(f"no {missing_tools('host')}")
    so = C.CDLL(str(build("host") / "libfwcore.so"))
    # a mirror that disagrees with the C layout would read garbage or write past the board: stop here
    assert layout_mismatches(so) == [], layout_mismatches(so)
    u8p, f32p = C.POINTER(C.c_uint8), C.POINTER(C.c_float)
    so.fw_crc32.argtypes = [C.c_uint32, C.c_char_p, C.c_uint32]
    so.fw_crc32.restype = C.c_uint32
    so.fw_crc32_f32.argtypes = [f32p, C.c_uint32]
    so.fw_crc32_f32.restype = C.c_uint32
    so.fw_xor_checksum.argtypes = [C.c_char_p, C.c_uint32]
    so.fw_xor_checksum.restype = C.c_uint8
    so.fw_frame.argtypes = [C.c_char_p, C.c_uint32, C.c_char_p, C.c_uint32]
    so.fw_frame.restype = C.c_uint32
    so.fw_unframe.argtypes = [C.c_char_p, C.c_uint32, C.POINTER(u8p)]
    so.fw_unframe.restype = C.c_int32
    so.fw_compensate.argtypes = [C.POINTER(FwCal), C.c_float, C.POINTER(C.c_int32), C.c_float, C.POINTER(C.c_int32)]
    so.fw_temp_c.argtypes = [C.POINTER(FwIdentity), C.c_int32]
    so.fw_temp_c.restype = C.c_float
    so.fw_fmt_f32.argtypes = [C.c_char_p, C.c_float]
    so.fw_fmt_f32.restype = C.c_uint32
    so.fw_parse_f32.argtypes = [C.c_char_p, C.c_uint32, f32p]
    so.fw_parse_f32.restype = C.c_int
    so.fw_rate_ratio.argtypes = [C.c_float, C.c_float]
    so.fw_rate_ratio.restype = C.c_uint32
    so.fw_fmt_u32.argtypes = [C.c_char_p, C.c_uint32]
    so.fw_fmt_u32.restype = C.c_uint32
    so.fw_fmt_i32.argtypes = [C.c_char_p, C.c_int32]
    so.fw_fmt_i32.restype = C.c_uint32
    for name in ("fw_tx_begin", "fw_tx_str"):
        getattr(so, name).argtypes = [C.c_void_p, C.c_char_p]
    so.fw_tx_raw.argtypes = [C.c_void_p, C.c_char_p, C.c_uint32]
    so.fw_tx_u32.argtypes = [C.c_void_p, C.c_uint32]
    so.fw_tx_hex32.argtypes = [C.c_void_p, C.c_uint32]
    so.fw_tx_i32.argtypes = [C.c_void_p, C.c_int32]
    so.fw_tx_f32.argtypes = [C.c_void_p, C.c_float]
    so.fw_tx_frame.argtypes = [C.c_void_p, C.c_char_p, C.c_uint32]
    so.fw_tx_frame.restype = C.c_uint32
    so.fw_board_sizeof.restype = C.c_uint32
    so.fw_board_init.argtypes = [C.c_void_p, C.POINTER(FwHal), C.POINTER(FwIdentity), C.c_uint8]
    so.fw_uart_rx.argtypes = [C.c_void_p, C.c_char_p, C.c_uint32]
    so.fw_can_rx.argtypes = [C.c_void_p, C.c_uint16, C.c_uint8, C.c_char_p]
    so.fw_sample.argtypes = [C.c_void_p, C.POINTER(FwRawSample)]
    so.fw_board_idle.argtypes = [C.c_void_p]
    so.fw_layout.argtypes = [C.c_char_p]
    so.fw_layout.restype = C.c_uint32
    so.fw_can_scale.argtypes = [C.POINTER(FwIdentity), f32p]
    so.fw_can_scale.restype = C.c_uint8
    so.fw_bridge_line.argtypes = [C.c_char_p, C.c_uint32, C.POINTER(FwIdentity), C.POINTER(FwRawSample)]
    so.fw_bridge_line.restype = C.c_int
    return so


def c_identity(i: Identity) -> FwIdentity:
    return FwIdentity(i.serial.encode(), i.sensor.encode(), i.fw.encode(), i.ug_per_lsb, i.t_lsb_per_c,
                      i.t_lsb_at_25c, i.odr_hz)


def f32_bits(v) -> bytes:
    return np.float32(v).tobytes()


class Board:
    """One board on the fake HAL. `out` holds the serial bytes sent, `can` the CAN frames."""

    def __init__(self, lib, ident: Identity = LIS, can_node: int = 0, slots=None) -> None:
        self.lib = lib
        self.ident = ident
        self.out = bytearray()
        self.can: list[tuple[int, bytes]] = []
        self.slots = slots if slots is not None else [bytearray(b"\xff" * SLOT) for _ in range(2)]
        self.fail_writes = 0
        self.writes: list[int] = []
        self._cbs = (UART_FN(self._uart), CAN_FN(self._can), NVM_RD(self._rd), NVM_WR(self._wr))
        self.hal = FwHal(None, self._cbs[0] if not can_node else UART_FN(), self._cbs[1] if can_node else CAN_FN(),
                         self._cbs[2], self._cbs[3])
        self.mem = C.create_string_buffer(lib.fw_board_sizeof())
        self.id = c_identity(ident)
        lib.fw_board_init(self.mem, C.byref(self.hal), C.byref(self.id), can_node)
        self.head = FwBoardHead.from_buffer(self.mem)
        self.t_us = 0

    def _uart(self, ctx, buf, n):
        self.out += C.string_at(buf, n)

    def _can(self, ctx, arb, dlc, data):
        self.can.append((arb, C.string_at(data, dlc)))

    def _rd(self, ctx, slot, buf, n):
        C.memmove(buf, bytes(self.slots[slot][:n]), n)
        return 0

    def _wr(self, ctx, slot, buf, n):
        self.writes.append(slot)
        if self.fail_writes:
            self.fail_writes -= 1
            self.slots[slot][:] = b"\xff" * SLOT
            self.slots[slot][:n // 2] = C.string_at(buf, n // 2)  # a failed program leaves half a record
            return -1
        self.slots[slot][:] = C.string_at(buf, n) + b"\xff" * (SLOT - n)
        return 0

    def rx(self, data: bytes) -> None:
        """Bytes from the station, then the target's idle pass (fw_board_idle): a long reply the
        command only recorded goes out, as on a board whose main loop found nothing else to do."""
        self.lib.fw_uart_rx(self.mem, data, len(data))
        self.lib.fw_board_idle(self.mem)

    def cmd(self, body: str) -> list:
        self.rx(sf.encode(body))
        return self.frames()

    def frames(self, parser=None) -> list:
        p = parser or sf.FrameParser()
        got = p.feed(bytes(self.out))
        assert p.stats.frames_bad_checksum == 0 and p.stats.frames_malformed == 0, (bytes(self.out), p.stats)
        self.out.clear()
        return got

    def lines(self) -> list[bytes]:
        raw = bytes(self.out)
        self.out.clear()
        return [ln for ln in raw.split(b"\n") if ln]

    def sample(self, acc, temp, dt_us: int = 320_000) -> None:
        s = FwRawSample(self.t_us & 0xFFFFFFFF, (C.c_int32 * 3)(*acc), temp)
        self.t_us += dt_us
        self.lib.fw_sample(self.mem, C.byref(s))

    def can_cmd(self, node: int, data: bytes) -> list[tuple[int, bytes]]:
        self.lib.fw_can_rx(self.mem, cf.CMD_BASE + node, len(data), data)
        got, self.can = self.can, []
        return got


# ---- pure codecs -------------------------------------------------------------------------------

def _random_f32(rng, n):
    """float32 values of every kind: uniform bit patterns, -0.0, denormals, huge, the usual range."""
    bits = rng.integers(0, 2**32, n, dtype=np.uint64).astype(np.uint32)
    vals = bits.view(np.float32)
    vals = vals[np.isfinite(vals)]
    special = np.array([0.0, -0.0, 1e-45, -1e-45, 1.1754942e-38, 1.17549435e-38, 3.4028235e38, -3.4028235e38,
                        0.1, -0.35, 1.4, -500.0, 3.9, -9.05], dtype=np.float32)
    usual = rng.normal(0, 1, n).astype(np.float32)
    return np.concatenate([special, vals, usual])


def test_crc32_matches_zlib(lib):
    rng = random.Random(1)
    for n in [0, 1, 2, 3, 4, 7, 64, 100, 1000]:
        for _ in range(20):
            data = bytes(rng.getrandbits(8) for _ in range(n))
            assert lib.fw_crc32(0, data, n) == zlib.crc32(data)
            seed = rng.getrandbits(32)
            assert lib.fw_crc32(seed, data, n) == zlib.crc32(data, seed)  # chaining, like zlib
    assert lib.fw_crc32(0, b"123456789", 9) == 0xCBF43926  # the CRC-32 check value


def test_crc32_f32_matches_cal_record(lib):
    rng = np.random.default_rng(2)
    vals = _random_f32(rng, 20000)
    for k in range(0, len(vals) - 18, 7):
        for n in (6, 12):
            v = vals[k:k + n]
            arr = (C.c_float * n)(*[float(x) for x in v])
            assert lib.fw_crc32_f32(arr, n) == crc32_f32(v), v
    # -0.0 is stored as +0.0 by both sides: the same CRC
    assert lib.fw_crc32_f32((C.c_float * 6)(-0.0, 0, 0, 0, 0, 0), 6) == crc32_f32([0.0] * 6)


def test_frame_matches_python_encode(lib):
    rng = random.Random(3)
    alphabet = bytes(range(0x20, 0x7F)).replace(b"$", b"")
    out = C.create_string_buffer(600)
    for _ in range(3000):
        body = bytes(rng.choice(alphabet) for _ in range(rng.randint(0, 200)))
        n = lib.fw_frame(body, len(body), out, 600)
        assert out.raw[:n] == sf.encode(body)
        assert lib.fw_xor_checksum(body, len(body)) == sf.checksum(body)
    assert lib.fw_frame(b"ID", 2, out, 6) == 0  # does not fit: nothing


def test_unframe_accepts_python_frames_and_rejects_corrupted(lib):
    rng = random.Random(4)
    alphabet = bytes(range(0x20, 0x7F)).replace(b"$", b"")
    body_p = C.POINTER(C.c_uint8)()
    for _ in range(3000):
        body = bytes(rng.choice(alphabet) for _ in range(rng.randint(1, 150)))
        line = sf.encode(body)[:-1]
        for ln in (line, line + b"\r"):
            n = lib.fw_unframe(ln, len(ln), C.byref(body_p))
            assert n == len(body) and C.string_at(body_p, n) == body
        k = rng.randrange(1, len(line) - 3)
        bad = bytearray(line)
        bad[k] ^= 1 << rng.randrange(7)
        if bytes(bad) != line and b"*" not in bytes(bad[k:k + 1]):
            assert lib.fw_unframe(bytes(bad), len(bad), C.byref(body_p)) == -1
        hh = line[-2:]
        wrong = b"%02X" % (int(hh, 16) ^ (1 << rng.randrange(8)))
        assert lib.fw_unframe(line[:-2] + wrong, len(line), C.byref(body_p)) == -1
        if hh.lower() != hh:  # the contract: upper-case hex only
            assert lib.fw_unframe(line[:-2] + hh.lower(), len(line), C.byref(body_p)) == -1
    for junk in (b"", b"$", b"ID*0D", b"$ID0D", b"$ID*0", b"$ID*G0", b"xx$ID*0D"):
        assert lib.fw_unframe(junk, len(junk), C.byref(body_p)) == -1


def _hard_f32() -> np.ndarray:
    """The float32 inputs where a shortest-digits formatter goes wrong first: every exponent (the
    denormal one included) with mantissa 0 (a power of two: the asymmetric rounding interval), 1,
    all ones and one half; the powers of ten float32(1eK); the normal/denormal border; both signs."""
    exps = np.arange(255, dtype=np.uint32) << 23
    bits = np.concatenate([exps, exps | 1, exps | 0x7FFFFF, exps | 0x400000, exps | 0x2AAAAA,
                           np.array([1, 2, 3, 7, 0x7FFFFE, 0x800001, 0x7F7FFFFE], dtype=np.uint32)])
    tens = np.array([float(f"1e{k}") for k in range(-45, 39)], dtype=np.float32)
    vals = np.concatenate([bits.view(np.float32), tens, (tens * np.float32(3)).astype(np.float32)])
    vals = vals[np.isfinite(vals) & (vals != 0)]
    return np.concatenate([vals, -vals])


def _c_fmt(lib, buf, v) -> str:
    n = lib.fw_fmt_f32(buf, float(v))
    return buf.raw[:n].decode()


def test_f32_shortest_text_matches_numpy(lib):
    """fw_fmt_f32 prints exactly fmt_f32 (numpy's shortest unique positional text) on 200k random bit
    patterns, the usual range and the hard cases, and the text reads back to the same float32.
    (All 2^32 patterns were compared once with firmware/tools/f32_exhaustive.cc: 0 differences.)"""
    rng = np.random.default_rng(5)
    buf = C.create_string_buffer(80)
    vals = np.concatenate([_random_f32(rng, 100_000), _hard_f32()])
    for v in vals:
        text = _c_fmt(lib, buf, v)
        assert text == sf.fmt_f32(float(v)), (hex(int(np.float32(v).view(np.uint32))), text)
        assert np.float32(float(text)).tobytes() == np.float32(v).tobytes() or v == 0
    for special, text in [(np.inf, "inf"), (-np.inf, "-inf"), (np.nan, "nan"), (0.0, "0"), (-0.0, "-0")]:
        assert _c_fmt(lib, buf, special) == text == sf.fmt_f32(special)


def test_f32_text_parses_like_the_station(lib):
    """C parses every text to float32(float(text)) bit for bit (the float64 first, then float32: the
    station's cal_record.to_f32). The core has no double: fw_parse_real (which also returned the
    float64) is gone, and so is every soft-double routine (test_firmware_arm checks the images)."""
    rng = np.random.default_rng(6)
    f = C.c_float()
    texts = []
    for v in np.concatenate([_random_f32(rng, 6000), _hard_f32()[::3]]):
        texts += ["%.9g" % v, "%.17g" % v, "%.5e" % v, repr(float(v) * (1 + 1e-7))]
    r = random.Random(6)
    for _ in range(5000):
        s = "".join(r.choice("0123456789") for _ in range(r.randint(1, 45)))
        k = r.randint(0, len(s))
        s = ("-" if r.random() < 0.5 else "") + s[:k] + "." + s[k:] + (f"e{r.randint(-70, 50)}" if r.random() < 0.5 else "")
        texts.append(s)
    # float32 midpoints written out exactly and nudged: where the float64-then-float32 rounding
    # (double rounding) differs from rounding the decimal once
    for bits in rng.integers(0x00800000, 0x7F000000, 300, dtype=np.uint64).astype(np.uint32):
        lo = float(np.uint32(bits).view(np.float32))
        hi = float(np.uint32(bits + 1).view(np.float32))
        mid = (lo + hi) / 2  # exact in float64
        texts += [repr(mid), f"{mid:.40e}", f"{mid * (1 + 2**-60):.40e}", f"{mid * (1 - 2**-60):.40e}"]
    texts += ["0", "-0", ".5", "5.", "1_000.25", " 2.5 ", "3.4028235e38", "3.4028236e38", "7.006492321624086e-46",
              "1e-46", "1e400", "inf", "-Infinity", "nan", "1.0000000596046448", "1.00000005960464477539062500001"]
    for s in texts:
        want = float(s)
        assert lib.fw_parse_f32(s.encode(), len(s), C.byref(f)) == 0, s
        with np.errstate(over="ignore"):
            w32 = np.float32(want)
        assert np.float32(f.value).tobytes() == w32.tobytes(), (s, f.value, w32)
    for s in ("", "-", ".", "e5", "1e", "1.2.3", "0x10", "1,5", "--1", "1e+", "_1", "abc"):
        f.value = 1234.5
        assert lib.fw_parse_f32(s.encode(), len(s), C.byref(f)) == -1, s
        assert f.value == 1234.5, s  # untouched on refusal
    assert not hasattr(lib, "fw_parse_real")


def _board_ratio(src: float, dst: float) -> int:
    """The decimation rule of fw_num.h, exactly, on rationals: k = src/dst rounded (halves up) when
    |src/dst - k| < 1e-6 + k 2^-24 and 1 <= k < 2^31 - 1, else 0 (not positive finite, dst > src).
    The k 2^-24 term is the float32 rounding of the station's rate text (relative 2^-24 at most)."""
    import math
    from fractions import Fraction

    if not (math.isfinite(src) and math.isfinite(dst) and src > 0 and dst > 0) or dst > src:
        return 0
    q = Fraction(src) / Fraction(dst)
    k = math.floor(q + Fraction(1, 2))
    if k >= 2**31 - 1:
        return 0
    return k if abs(q - k) < Fraction(1, 10**6) + Fraction(k, 2**24) else 0


def test_rate_ratio_follows_its_rule(lib):
    """fw_rate_ratio (integers on the float32 values) against the rule evaluated on exact rationals:
    exact divisors, near misses by a few ulps, the 1e-6 + k 2^-24 borders from both sides, junk."""
    f32 = np.float32
    pairs = []
    for src in [3.125, 100.0, 400.0, 1600.0, 800.0, 25.0, 6.25, 1000 / 3, 4000.0, 1e-40, 3e38]:
        s32 = f32(src)
        for k in list(range(1, 300)) + [1000, 3125, 10**5, 10**6, 2**22, 2**23, 2**24, 2**31 - 2, 2**31 - 1, 2**31,
                                        2**33]:
            d32 = f32(s32 / f32(k))
            for nudge in (-3, -1, 0, 1, 3):  # neighbouring float32 values
                pairs.append((s32, np.array([int(d32.view(np.uint32)) + nudge], np.int64).astype(np.uint32)
                              .view(np.float32)[0]))
            tol = 1e-6 + k * 2.0**-24
            for side in (0.9, 1.1):  # inside / just outside the window, above and below k
                for sign in (1, -1):
                    pairs.append((s32, f32(float(s32) / (k + sign * side * tol))))
    rng = np.random.default_rng(7)
    rand = rng.integers(0, 2**32, (20_000, 2), dtype=np.uint64).astype(np.uint32).view(np.float32)
    pairs += [(a, b) for a, b in rand]
    junk = [0.0, -0.0, -1.0, np.inf, -np.inf, np.nan, 1e-45, 3.4028235e38]
    pairs += [(f32(a), f32(b)) for a in junk + [100.0] for b in junk + [100.0, 50.0]]
    accepted = refused = 0
    for src, dst in pairs:
        got = lib.fw_rate_ratio(float(src), float(dst))
        assert got == _board_ratio(float(src), float(dst)), (float(src), float(dst), got)
        accepted += got > 0
        refused += got == 0
    assert accepted > 3000 and refused > 20_000  # both sides of the rule were exercised
    assert lib.fw_rate_ratio(3.125, 0.625) == 5 and lib.fw_rate_ratio(100.0, f32(100 / 3)) == 3
    assert lib.fw_rate_ratio(3.125, f32(1e-3)) == 3125  # float32(0.001): 1.5e-4 off 3125 in the ratio
    assert lib.fw_rate_ratio(3.125, f32(0.1)) == 0  # 31.25


def test_rate_ratio_accepts_every_rate_the_simulated_board_accepts(lib):
    """The station writes a rate as decimal text; the simulated board (serial_pty._ratio) decides on
    its float64, the C board on its float32. Every rate the simulated board accepts must be accepted
    by the C board with the same k (else a profile that runs on the simulator fails on hardware),
    and the C board accepts no rate whose float32 is farther from src/k than the rule allows."""
    from drivers.sim.serial_pty import _ratio

    rng = np.random.default_rng(17)
    checked = 0
    for src in (3.125, 100.0, 400.0, 1600.0, 1000 / 3, 6.25):
        s32 = float(np.float32(src))
        for k in [1, 2, 3, 5, 7, 10, 16, 25, 100, 3125, 10**4, 10**5, 10**6, 2**20]:
            for rel in np.concatenate([[0.0], rng.uniform(-0.99e-6, 0.99e-6, 6) / k]):
                rate = s32 / (k * (1 + float(rel)))  # a float64 rate inside the simulated board's window
                if _ratio(s32, rate) != k:
                    continue
                text = repr(rate)
                assert lib.fw_rate_ratio(s32, float(np.float32(float(text)))) == k, (src, k, text)
                checked += 1
    assert checked > 400
    assert _ratio(3.125, 1e-3) == 3125 and lib.fw_rate_ratio(3.125, float(np.float32(1e-3))) == 3125


def test_int_formatting_writes_exactly_the_text(lib):
    """fw_fmt_u32 / fw_fmt_i32 print str(v) and write nothing past the NUL (callers size their
    buffers for the text: the word-wide copies inside must not spill)."""
    rng = random.Random(8)
    us = [0, 1, 9, 10, 99, 100, 999, 1000, 9999, 10**5, 10**8 - 1, 10**8, 10**9 - 1, 10**9, 2**32 - 1]
    us += [rng.getrandbits(rng.randint(1, 32)) for _ in range(3000)]
    for u in us:
        buf = C.create_string_buffer(b"\xaa" * 16, 16)
        n = lib.fw_fmt_u32(buf, u)
        assert buf.raw[:n + 1] == str(u).encode() + b"\0" and buf.raw[n + 1:] == b"\xaa" * (15 - n), u
    for i in [0, -1, 1, -9, -10, -2**31, 2**31 - 1] + [rng.randint(-2**31, 2**31 - 1) for _ in range(3000)]:
        buf = C.create_string_buffer(b"\xaa" * 16, 16)
        n = lib.fw_fmt_i32(buf, i)
        assert buf.raw[:n + 1] == str(i).encode() + b"\0" and buf.raw[n + 1:] == b"\xaa" * (15 - n), i


def test_reply_builder_frames_like_python(lib):
    """The fw_tx_* builder (numbers formatted in place) frames exactly what sf.encode makes of the same
    fields, also when the body is nearly full: a field that fits to the last byte is kept, one that
    does not marks the reply overflowed and nothing is framed."""
    rng = np.random.default_rng(9)
    out = C.create_string_buffer(800)
    for trial in range(400):
        t = FwTx()
        lib.fw_tx_begin(C.byref(t), b"D" if trial % 2 else b"ID")
        parts = ["D" if trial % 2 else "ID"]
        pad = int(rng.integers(0, TX_BODY_MAX))  # a raw prefix to move the builder towards its end
        raw = ("x" * pad).encode()
        lib.fw_tx_raw(C.byref(t), raw, len(raw))
        parts[0] += "x" * pad
        for _ in range(int(rng.integers(1, 20))):
            kind = int(rng.integers(0, 5))
            if kind == 0:
                v = int(rng.integers(0, 2**32))
                lib.fw_tx_u32(C.byref(t), v)
                parts.append(str(v))
            elif kind == 1:
                v = int(rng.integers(-2**31, 2**31))
                lib.fw_tx_i32(C.byref(t), v)
                parts.append(str(v))
            elif kind == 2:
                v = rng.integers(0, 2**32, dtype=np.uint64).astype(np.uint32).view(np.float32)
                lib.fw_tx_f32(C.byref(t), float(v))
                parts.append(sf.fmt_f32(float(v)))
            elif kind == 3:
                v = int(rng.integers(0, 2**32))
                lib.fw_tx_hex32(C.byref(t), v)
                parts.append(sf.fmt_crc(v))
            else:
                lib.fw_tx_str(C.byref(t), b"SFER")
                parts.append("SFER")
        body = ",".join(parts).encode()
        n = lib.fw_tx_frame(C.byref(t), out, 800)
        if len(body) <= TX_BODY_MAX:
            assert (t.overflow, t.len) == (0, len(body)) and out.raw[:n] == sf.encode(body), trial
        else:
            assert t.overflow == 1 and n == 0, trial
    # exactly full: TX_BODY_MAX bytes accepted, one more refused
    t = FwTx()
    lib.fw_tx_begin(C.byref(t), b"S")
    lib.fw_tx_raw(C.byref(t), b"y" * (TX_BODY_MAX - 12), TX_BODY_MAX - 12)
    lib.fw_tx_u32(C.byref(t), 4294967295)  # 1 + (TX_BODY_MAX - 12) + 11 bytes: full
    assert (t.len, t.overflow) == (TX_BODY_MAX, 0)
    lib.fw_tx_u32(C.byref(t), 0)
    assert t.overflow == 1 and lib.fw_tx_frame(C.byref(t), out, 800) == 0


def test_pow10_table_is_what_its_generator_makes():
    """fw_num_pow10.h is the output of fw_num_pow10.py (which also proves its integer shortcuts over
    the float32 exponent range): nobody edited the table by hand."""
    import subprocess
    import sys
    from drivers.sim.firmware_build import FIRMWARE_DIR

    proc = subprocess.run([sys.executable, str(FIRMWARE_DIR / "core" / "fw_num_pow10.py"), "--check"],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


# ---- compensation --------------------------------------------------------------------------------

def _coefficients(rng, sfem: bool):
    tdb = rng.uniform(-1.2, 1.4, 3)
    tdsf = rng.uniform(-500.0, 0.0, 3)
    a = np.eye(3) + rng.uniform(-0.02, 0.02, (3, 3))
    b = rng.uniform(-0.05, 0.05, 3)
    return to_f32([*tdb, *tdsf]), (to_f32([*a.reshape(-1), *b]) if sfem else None)


@pytest.mark.parametrize("ident,full_scale", [(LIS, 32767), (ADXL, 524287)])
def test_compensate_matches_board_nvm(lib, ident, full_scale):
    """fw_compensate (float32, in counts) vs CalFirmware.compensate_counts (float64, through g).

    Tolerance: |diff| <= 1 count. The C result is ~10 float32 operations on values up to
    full_scale counts; each rounds by at most 2^-24 relative, so the C value before rounding is
    within ~10 * 2^-24 * 5.3e5 = 0.3 counts (ADXL355, 20 bit), 0.02 counts (LIS3DSH) of the exact
    one: after rint the two can differ by one count only when the exact value lies that close to a
    .5 boundary, so most samples are equal (asserted) and none differs by more than one."""
    rng = np.random.default_rng(7 if ident is LIS else 8)
    cid = c_identity(ident)
    total = equal = 0
    for trial in range(60):
        thermal, sfem = _coefficients(rng, sfem=trial % 2 == 1)
        fwc = CalFirmware()
        fwc.nvm.thermal = thermal
        fwc.nvm.sfem = sfem
        cal = FwCal((C.c_float * 6)(*thermal), (C.c_float * 12)(*(sfem or [0.0] * 12)), crc32_f32(thermal),
                    crc32_f32(sfem) if sfem else 0, 1 if sfem else 0, 1)
        n = 200
        acc = rng.integers(-full_scale, full_scale + 1, (n, 3))
        temp_c_want = rng.uniform(-40, 85, n)
        tcounts = np.rint(ident.t_lsb_at_25c + (temp_c_want - 25) * ident.t_lsb_per_c).astype(np.int64)
        want = fwc.compensate_counts(acc, ident.temp_c(tcounts), ident.ug_per_lsb)
        out = (C.c_int32 * 3)()
        for k in range(n):
            tc = lib.fw_temp_c(C.byref(cid), int(tcounts[k]))
            assert abs(tc - ident.temp_c(tcounts[k])) < 1e-4
            lib.fw_compensate(C.byref(cal), ident.ug_per_lsb, (C.c_int32 * 3)(*acc[k].tolist()), tc, out)
            diff = np.abs(np.array(out[:]) - want[k])
            assert diff.max() <= 1, (thermal, sfem, acc[k], tcounts[k], out[:], want[k])
            total += 3
            equal += int((diff == 0).sum())
    assert equal / total >= (0.99 if ident is LIS else 0.95), equal / total
    # the compensation really does something here (not an identity that would pass trivially)
    fwc = CalFirmware()
    fwc.nvm.thermal = to_f32([1.0, -1.0, 0.5, -300, -200, -100])
    cal = FwCal((C.c_float * 6)(*fwc.nvm.thermal), (C.c_float * 12)(), 0, 0, 0, 1)
    raw = [1000, -1000, 16000]
    tc_count = int(round(ident.t_lsb_at_25c + 40 * ident.t_lsb_per_c))
    out = (C.c_int32 * 3)()
    lib.fw_compensate(C.byref(cal), ident.ug_per_lsb, (C.c_int32 * 3)(*raw), lib.fw_temp_c(C.byref(cid), tc_count), out)
    want = fwc.compensate_counts(np.array([raw]), ident.temp_c(np.array([tc_count])), ident.ug_per_lsb)[0]
    assert list(out) != raw and np.abs(np.array(out[:]) - want).max() <= 1


def test_compensate_rounds_half_even_and_saturates(lib):
    cal = FwCal((C.c_float * 6)(), (C.c_float * 12)(2.5, 0, 0, 0, 1, 0, 0, 0, -3.0e9), 0, 0, 1, 1)
    out = (C.c_int32 * 3)()
    # SFEM with b = 0: x' = 2.5 * 1 = 2.5 -> 2 (rint), y = 3 (exact), z = -3e9 * 1 -> saturated
    lib.fw_compensate(C.byref(cal), 60.0, (C.c_int32 * 3)(1, 3, 1), 25.0, out)
    assert list(out) == [2, 3, -2**31]


# ---- the board on a fake HAL: serial link (design 3.1) -------------------------------------------

def _ident_with(i: Identity, **kw) -> Identity:
    import dataclasses
    return dataclasses.replace(i, **kw)


def _flash_record(slots) -> BoardRecordInfo:
    """The `rec_*` keys a board must report for this flash (docs/design.md 3.1), from the
    bytes alone (tests/firmware_nvm.py decodes them): the newest valid record, `fallback` when the
    other slot is neither erased nor valid, `empty` / `corrupt` when no slot is valid."""
    recs = [decode_slot(k, bytes(slots[k])) for k in range(2)]
    bad = [recs[k] is None and bytes(slots[k]) != b"\xff" * SLOT for k in range(2)]
    valid = [r for r in recs if r is not None]
    if valid:
        r = max(valid, key=lambda x: x.generation)
        return BoardRecordInfo(r.version, r.generation, r.slot, "fallback" if bad[1 - r.slot] else "ok")
    return BoardRecordInfo(0, 0, None, "corrupt" if any(bad) else "empty")


def _calr(values, comp: bool, slots) -> sf.CalReadFrame:
    """The C frame a board answers $CALR with: the base fields of design 3.1 and the record keys."""
    return sf.CalReadFrame(values, crc32_f32(values), comp, _flash_record(slots))


@pytest.mark.parametrize("ident", [LIS, ADXL])
def test_identity_start_samples_stop(lib, ident):
    b = Board(lib, ident)
    assert b.out == b"" and b.head.nvm_status == 1  # virgin: EMPTY, no error frame
    b.rx(b"$ID*0D\n")
    raw = bytes(b.out)
    base, keys = split_keys(raw[1:-4].decode().split(","))
    assert base == sf.IdentityFrame(ident).encode()[1:-4].decode().split(",")  # fmt_number: 60,1,0 / 3.9,-9.05,1885
    # the keys of a board that was never told its reset cause (fw_board_set_boot), on erased flash
    health = _ident_with(ident, reset_cause="unknown", boots=0, record=BoardRecordInfo(0, 0, None, "empty"),
                         caps={"scal", "sfem3"}, sensor_reinits=0)
    assert raw == sf.IdentityFrame(health).encode(), keys  # byte for byte, keys in the contract's order
    (frame,) = b.frames()
    assert frame.identity == ident and frame.identity.record == health.record
    b.sample([1, 2, 3], 4)
    assert b.out == b""  # not started: nothing
    assert b.cmd("START") == [sf.AckFrame("START")]
    rows = [([k, -k, 16000 + k], 10 + k) for k in range(5)]
    t0 = b.t_us
    for acc, t in rows:
        b.sample(acc, t)
    got = b.frames()
    assert got == [sf.SampleFrame(k, t0 + 320_000 * k, *acc, t) for k, (acc, t) in enumerate(rows)]
    assert b.cmd("STOP") == [sf.AckFrame("STOP")]
    b.sample([1, 2, 3], 4)
    assert b.out == b""
    assert b.cmd("START") == [sf.AckFrame("START")]
    b.sample([1, 2, 3], 4)
    assert b.frames()[0].seq == 5  # seq runs on across STOP/START, like the simulated board


def test_seq_wraps_at_uint32(lib):
    b = Board(lib)
    b.cmd("START")
    b.head.seq = 0xFFFFFFFE
    for _ in range(3):
        b.sample([0, 0, 0], 0)
    assert [f.seq for f in b.frames()] == [0xFFFFFFFE, 0xFFFFFFFF, 0]


def test_odr_decimation_like_the_simulated_board(lib):
    from drivers.sim.serial_pty import _ratio
    b = Board(lib)
    for rate in ["3.125", "1.5625", "0.625", "0.3125", "0.0625", "1", "3.2", "6.25", "0", "-1", "0.1",
                 "1e-3", "0.78125", "1.0416666666666667", "abc", "nan", "inf"]:
        try:
            k = _ratio(3.125, float(rate))
        except ValueError:
            k = None
        got = b.cmd(f"ODR,{rate}")
        if k is None:
            assert got == [sf.ErrorFrame("ODR", f"unsupported rate {rate}")], rate
        else:
            assert got == [sf.AckFrame("ODR", (rate,))], rate
            assert b.head.decim == k
    assert b.cmd("ODR") == [sf.ErrorFrame("ODR", "need 1 value")]
    assert b.cmd("ODR,0.625") == [sf.AckFrame("ODR", ("0.625",))]
    (ident,) = b.cmd("ID")
    assert ident.identity.odr_hz == 0.625
    b.cmd("START")
    for k in range(12):
        b.sample([k, 0, 0], 0)
    assert [f.ax for f in b.frames()] == [0, 5, 10]  # every 5th, starting with the first one


def test_garbage_is_counted_and_skipped(lib):
    b = Board(lib)
    good = sf.encode("CALR")  # checksum 0x1F... any frame whose HH has a letter
    hh = b"%02X" % sf.checksum(b"CALR")
    cases = [
        b"hello\n",                                  # garbage line
        b"\n",                                       # empty line
        b"$CALR*00\n",                               # bad checksum
        sf.encode("NOPE"),                           # unknown type
        b"$*00\n",                                   # empty body
        b"$ID\n",                                    # short line, no checksum
        b"$ID*0\n",                                  # short checksum
        b"x" * 500 + b"\n",                          # over-long line
        b"$" + b"A" * 300 + b"*00\n",                # over-long frame
        sf.encode(b"START\x80"),                     # non-ASCII body
    ]
    if hh != hh.lower():
        cases.append(good[:-3] + hh.lower() + b"\n")  # lower-case checksum: the contract says upper
    for raw in cases:
        before = b.head.rx_bad_frames
        b.rx(raw)
        assert b.out == b"" and b.head.rx_bad_frames == before + 1, raw
    before = b.head.rx_bad_frames
    b.rx(b"junk" + sf.encode("STOP")[:-1] + b"\r\n")  # junk before a frame: counted, frame kept; CR LF ok
    assert b.frames() == [sf.AckFrame("STOP")] and b.head.rx_bad_frames == before + 1
    raw = sf.encode("ID") + sf.encode("START")             # split anywhere, several per read
    for k in range(len(raw)):
        b.rx(raw[k:k + 1])
    assert [type(f) for f in b.frames()] == [sf.IdentityFrame, sf.AckFrame]


def test_wrong_arguments_get_error_replies(lib):
    b = Board(lib)
    cases = {
        "ID,1": "ID", "START,x": "START", "STOP,1": "STOP", "CALR,1": "CALR", "SFER,1": "SFER", "SCRR,0": "SCRR",
        "CALW,1,2,3,4,5": "CALW", "CALW,1,2,3,4,5,6,7": "CALW", "CALW,1,2,3,4,5,nan": "CALW",
        "CALW,1,2,3,4,5,inf": "CALW", "CALW,1,2,3,4,5,1e39": "CALW", "CALW,1,2,3,4,5,x": "CALW",
        "SFEW,1,2,3": "SFEW", "SFEW," + ",".join(["1"] * 11) + ",-inf": "SFEW",
        "COMP": "COMP", "COMP,2": "COMP", "COMP,1,1": "COMP", "SCAL,on": "SCAL",
    }
    for body, code in cases.items():
        got = b.cmd(body)
        assert len(got) == 1 and isinstance(got[0], sf.ErrorFrame) and got[0].code == code and got[0].text, body
    assert b.writes == []  # nothing was stored
    assert b.head.rx_bad_frames == 0


def _parse_record(slot: bytes) -> dict:
    """The NVM record as fw_nvm.h documents it, decoded independently."""
    magic, version, length, gen = struct.unpack_from("<IHHI", slot, 0)
    return dict(magic=magic, version=version, length=length, gen=gen,
                thermal=struct.unpack_from("<6f", slot, 12), thermal_crc=struct.unpack_from("<I", slot, 36)[0],
                has_sfem=slot[40], sfem=struct.unpack_from("<12f", slot, 44), sfem_crc=struct.unpack_from("<I", slot, 92)[0],
                comp=slot[96], crc=struct.unpack_from("<I", slot, 100)[0], crc_ok=zlib.crc32(slot[:100]) == struct.unpack_from("<I", slot, 100)[0])


def test_calibration_write_read_and_nvm_layout(lib):
    rng = np.random.default_rng(11)
    b = Board(lib)
    zeros = (0.0,) * 6
    assert bytes(b.cmd_raw("CALR")) == _calr(zeros, False, b.slots).encode()
    assert b.cmd("SFER") == [sf.ErrorFrame("SFER", "no SFEM stored")]
    for k in range(6):
        thermal, sfem = _coefficients(rng, sfem=True)
        if k == 0:
            thermal = to_f32([-0.0, 1e-45, -1.2, -0.35, -500, 3.4028235e38])  # edge values round-trip too
        assert bytes(b.cmd_raw(sf.cmd_calw(thermal[:3], thermal[3:])[1:-4].decode())) == \
            sf.AckFrame("CALW", (sf.fmt_crc(crc32_f32(thermal)),)).encode()
        rb = b.cmd_raw("CALR")
        assert bytes(rb) == _calr(thermal, False, b.slots).encode()
        assert _flash_record(b.slots) == BoardRecordInfo(1, len(b.writes), b.writes[-1], "ok")
        (c,) = sf.FrameParser().feed(bytes(rb))
        assert c.values == thermal and c.crc == crc32_f32(thermal)
        a, bb = np.array(sfem[:9]).reshape(3, 3), sfem[9:]
        assert b.cmd(sf.cmd_sfew(a, bb)[1:-4].decode()) == [sf.AckFrame("SFEW", (sf.fmt_crc(crc32_f32(sfem)),))]
        assert bytes(b.cmd_raw("SFER")) == sf.SfemReadFrame(sfem, crc32_f32(sfem)).encode()
        rec = _parse_record(bytes(b.slots[b.writes[-1]]))
        assert rec["magic"] == 0x4C414346 and rec["version"] == 1 and rec["length"] == 104 and rec["crc_ok"]
        assert rec["gen"] == len(b.writes) and to_f32(rec["thermal"]) == thermal and rec["thermal_crc"] == crc32_f32(thermal)
        assert rec["has_sfem"] == 1 and to_f32(rec["sfem"]) == sfem and rec["sfem_crc"] == crc32_f32(sfem)
        assert bytes(b.slots[b.writes[-1]][104:]) == b"\xff" * (SLOT - 104)
    assert b.writes == [0, 1] * 6  # A/B: always the slot not holding the newest record
    assert b.cmd("COMP,1") == [sf.AckFrame("COMP")]
    assert b.cmd("COMP,1") == [sf.AckFrame("COMP")]  # unchanged: no flash write
    assert len(b.writes) == 13 and _parse_record(bytes(b.slots[0]))["comp"] == 1
    (c,) = b.cmd("CALR")
    assert c.comp and c.values == thermal
    # power cycle: a new board on the same flash applies the newest record, no error frame
    b2 = Board(lib, slots=b.slots)
    assert b2.out == b"" and b2.head.nvm_status == 0 and b2.head.nvm_seq == 13
    assert b2.cmd("CALR") == [_calr(thermal, True, b.slots)]
    assert b2.cmd("SFER") == [sf.SfemReadFrame(sfem, crc32_f32(sfem))]


def _cmd_raw(self, body: str) -> bytes:
    self.rx(sf.encode(body))
    raw = bytes(self.out)
    self.out.clear()
    return raw


Board.cmd_raw = _cmd_raw


def test_failed_flash_write_keeps_the_previous_record(lib):
    b = Board(lib)
    old = to_f32([0.5, -0.5, 0.25, -100, -200, -300])
    b.cmd(sf.cmd_calw(old[:3], old[3:])[1:-4].decode())
    b.fail_writes = 1
    assert b.cmd("CALW,1,1,1,-1,-1,-1") == [sf.ErrorFrame("CALW", "flash write failed")]
    # the half-programmed slot 1 makes the record in force a fallback now, as it would after a restart
    assert _flash_record(b.slots) == BoardRecordInfo(1, 1, 0, "fallback")
    assert b.cmd("CALR") == [_calr(old, False, b.slots)]
    b.fail_writes = 1
    assert b.cmd("COMP,1") == [sf.ErrorFrame("COMP", "flash write failed")]
    assert b.cmd("CALR")[0].comp is False
    # power cycle: the half-programmed slot is reported, the previous record applied
    b2 = Board(lib, slots=b.slots)
    assert b2.frames() == [sf.ErrorFrame("NVM", "calibration record CRC mismatch in slot 1")]
    assert b2.cmd("CALR") == [_calr(old, False, b.slots)]
    new = to_f32([1, 1, 1, -1, -1, -1])
    assert b2.cmd("CALW,1,1,1,-1,-1,-1") == [sf.AckFrame("CALW", (sf.fmt_crc(crc32_f32(new)),))]
    assert b2.writes == [1]  # over the broken slot, never over the good one
    assert b2.cmd("CALR") == [_calr(new, False, b2.slots)] and _flash_record(b2.slots).rec_state == "ok"
    assert Board(lib, slots=b2.slots).frames() == []


def test_corrupt_records_at_boot(lib):
    b = Board(lib)
    first = to_f32([0.5, -0.5, 0.25, -100, -200, -300])
    second = to_f32([1.0, -1.0, 0.5, -50, -60, -70])
    b.cmd(sf.cmd_calw(first[:3], first[3:])[1:-4].decode())
    b.cmd("COMP,1")
    b.cmd(sf.cmd_calw(second[:3], second[3:])[1:-4].decode())
    newest = b.writes[-1]
    # one flipped bit in the newest record (in a value: only the CRCs can tell)
    slots = [bytearray(s) for s in b.slots]
    slots[newest][20] ^= 0x04
    b2 = Board(lib, slots=slots)
    assert b2.frames() == [sf.ErrorFrame("NVM", f"calibration record CRC mismatch in slot {newest}")]
    assert b2.head.nvm_status == 0
    assert b2.cmd("CALR") == [_calr(first, True, slots)]  # the older valid record
    assert _flash_record(slots).rec_state == "fallback"
    # both slots corrupt: zeros, uncompensated, CALR refused until a new CALW succeeds
    slots[1 - newest][60] ^= 0x80
    b3 = Board(lib, slots=[bytearray(s) for s in slots])
    assert b3.frames() == [sf.ErrorFrame("NVM", "calibration record CRC mismatch in slot 0"),
                           sf.ErrorFrame("NVM", "calibration record CRC mismatch in slot 1")]
    assert b3.head.nvm_status == 2 and b3.head.cal.comp == 0 and list(b3.head.cal.thermal) == [0.0] * 6
    assert b3.cmd("CALR") == [sf.ErrorFrame("CALR", "calibration record corrupt")]
    assert b3.cmd("SFER") == [sf.ErrorFrame("SFER", "calibration record corrupt")]
    assert b3.cmd("COMP,1") == [sf.ErrorFrame("COMP", "calibration record corrupt")]
    assert b3.cmd("SFEW," + ",".join(["1"] * 12)) == [sf.ErrorFrame("SFEW", "calibration record corrupt")]
    b3.cmd("START")
    b3.sample([1000, -1000, 16000], 40)
    assert b3.frames() == [sf.SampleFrame(0, 0, 1000, -1000, 16000, 40)]  # raw counts
    assert b3.cmd(sf.cmd_calw(second[:3], second[3:])[1:-4].decode())[0].command == "CALW"
    # stored in slot 0; slot 1 still neither erased nor valid: a fallback until it is written over
    assert b3.cmd("CALR") == [_calr(second, False, b3.slots)]
    assert _flash_record(b3.slots) == BoardRecordInfo(1, 1, 0, "fallback")
    # a record with a valid record CRC but the wrong magic / version is not applied either
    rec = bytearray(b.slots[newest])
    rec[4] = 2
    struct.pack_into("<I", rec, 100, zlib.crc32(bytes(rec[:100])))
    b4 = Board(lib, slots=[rec if k == newest else bytearray(b"\xff" * SLOT) for k in range(2)])
    assert b4.frames() == [sf.ErrorFrame("NVM", f"calibration record CRC mismatch in slot {newest}")]
    assert b4.head.nvm_status == 2


@pytest.mark.parametrize("ident", [LIS, ADXL])
def test_compensated_d_frames(lib, ident):
    rng = np.random.default_rng(12)
    b = Board(lib, ident)
    thermal, sfem = _coefficients(rng, sfem=True)
    fwc = CalFirmware()
    fwc.nvm.thermal, fwc.nvm.sfem, fwc.nvm.comp = thermal, sfem, True
    b.cmd(sf.cmd_calw(thermal[:3], thermal[3:])[1:-4].decode())
    b.cmd(sf.cmd_sfew(np.array(sfem[:9]).reshape(3, 3), sfem[9:])[1:-4].decode())
    b.cmd("COMP,1")
    b.cmd("START")
    n = 300
    fs = 30000 if ident is LIS else 500000
    acc = rng.integers(-fs, fs, (n, 3))
    tc = np.rint(ident.t_lsb_at_25c + rng.uniform(-60, 60, n) * ident.t_lsb_per_c).astype(np.int64)
    for k in range(n):
        b.sample(acc[k].tolist(), int(tc[k]))
    got = np.array([[f.ax, f.ay, f.az] for f in b.frames()])
    want = fwc.compensate_counts(acc, ident.temp_c(tc), ident.ug_per_lsb)
    assert np.abs(got - want).max() <= 1 and (got == want).mean() > 0.95
    assert np.abs(got - acc).max() > 10  # compensation is on


def test_selfcal_frames(lib):
    b = Board(lib, ADXL)
    assert b.cmd("SCRR") == [sf.ErrorFrame("SCRR", "no result: no segments")]
    assert b.cmd("SCAL,1") == [sf.AckFrame("SCAL")] and b.head.selfcal_on == 1
    # runs without START: a steady orientation at a steady temperature long enough for segments
    for k in range(4000):
        b.sample([0, 0, 256410], 1885, dt_us=10_000)
    lines = b.lines()
    for ln in lines:  # G frames (if the calibrator saved segments): framing and round-trip floats
        body = ln[1:-3]
        assert ln == sf.encode(body)[:-1]
        f = body.decode().split(",")
        assert f[0] == "G" and len(f) == 9
        int(f[1]), int(f[2]), int(f[3]), int(f[8])
        assert all(np.isfinite(float(x)) for x in f[4:8])
        assert abs(float(f[6]) - 256410 * 3.9e-6) < 1e-3 and abs(float(f[7]) - 25.0) < 1e-3
    assert len(lines) >= 1  # 40 s steady: the calibrator saved at least one segment
    got = b.cmd_raw("SCRR")
    assert got.startswith(b"$R,") or got.startswith(b"$E,SCRR,no result: ")
    assert b.cmd("SCAL,0") == [sf.AckFrame("SCAL")] and b.head.selfcal_on == 0


def test_bridge_lines(lib):
    ident, s = FwIdentity(), FwRawSample()
    line = sf.encode("B,AX0001,ADXL355,3.9,-9.05,1885,3.125")[:-1]
    assert lib.fw_bridge_line(line, len(line), C.byref(ident), C.byref(s)) == 1
    assert (ident.serial, ident.sensor, ident.fw) == (b"AX0001", b"ADXL355", b"fw-c-1.0")
    assert [ident.ug_per_lsb, ident.t_lsb_per_c, ident.odr_hz] == [np.float32(3.9), np.float32(-9.05), 3.125]
    line = sf.encode("S,4294967297,-5,6,-524288,1900")[:-1] + b"\r"
    assert lib.fw_bridge_line(line, len(line), C.byref(ident), C.byref(s)) == 2
    assert (s.t_us, list(s.acc), s.temp) == (1, [-5, 6, -524288], 1900)
    for bad in ("S,1,2,3,4", "S,1,2,3,4,x", "B,AX,ADXL355,0,1,0,3.125", "Q,1", "S,1,2,3,4,99999999999"):
        line = sf.encode(bad)[:-1]
        assert lib.fw_bridge_line(line, len(line), C.byref(ident), C.byref(s)) == 0, bad
    line = sf.encode("S,1,2,3,4,5")[:-3] + b"00"
    assert lib.fw_bridge_line(line, len(line), C.byref(ident), C.byref(s)) == 0


def test_mirrors_match_the_c_layout(lib):
    """The ctypes mirrors are the C structs (fw_layout: sizeof/offsetof by name), and the check can
    fail: a mirror with the old 16-byte serial is caught, naming the struct, and an unknown name is
    no offset at all."""
    assert layout_mismatches(lib) == []
    assert lib.fw_layout(b"fw_board_t") == lib.fw_board_sizeof()
    assert lib.fw_layout(b"fw_identity_t.serial") == 0 and lib.fw_layout(b"no_such_t.x") == NO_LAYOUT

    class OldIdentity(C.Structure):  # before issue 42: FW_SERIAL_MAX 15
        _fields_ = [("serial", C.c_char * 16), *FwIdentity._fields_[1:]]

    bad = layout_mismatches(lib, {**MIRRORS, "fw_identity_t": OldIdentity})
    assert bad and bad[0].startswith("sizeof fw_identity_t") and any("fw_identity_t.sensor" in x for x in bad)


def _reply_state(lib, b: Board) -> tuple[int, int]:
    """(pending, numbers formatted so far) of the board's long reply, through fw_layout's offsets."""
    base = lib.fw_layout(b"fw_board_t.reply")
    pending = C.c_uint8.from_buffer(b.mem, base + lib.fw_layout(b"fw_reply_t.pending")).value
    done = C.c_uint8.from_buffer(b.mem, base + lib.fw_layout(b"fw_reply_t.next")).value
    return pending, done


def test_long_replies_go_out_whole_a_few_numbers_per_sample(lib):
    """$SFER (12 numbers) is only recorded by the command; each fw_sample formats REPLY_STEP more
    numbers after its own D frame, and the S frame goes out whole, byte for byte what the station's
    codec makes of the stored values (the same as answering at once), after ceil(12 / REPLY_STEP)
    samples. fw_board_idle finishes a reply at once (a silent sensor still gets an answer); a command
    arriving while a reply is pending sends that reply first (replies keep their order)."""
    # denormals print 47-48 characters (the longest fw_fmt_f32 writes): the body near its worst case.
    # Stored in the flash image directly: a $SFEW of them would pass the 512-byte line.
    sfem = to_f32([(-1) ** k * (k + 1) * 1.4e-45 for k in range(12)])
    thermal = to_f32([0.5, -0.5, 0.25, -100, -200, -300])
    b = Board(lib, slots=[bytearray(slot_image(encode_record(1, thermal, sfem))), bytearray(b"\xff" * SLOT)])
    assert b.out == b"" and b.head.cal.has_sfem == 1
    want = sf.SfemReadFrame(sfem, crc32_f32(sfem)).encode()
    assert len(want) > 560
    b.cmd("START")
    request = sf.encode("SFER")
    lib.fw_uart_rx(b.mem, request, len(request))  # no idle pass: a board with samples back to back
    assert b.out == b"" and _reply_state(lib, b) == (1, 0)
    steps = -(-12 // REPLY_STEP)
    for k in range(steps):
        b.sample([k, 0, 16000], 25)
        if k < steps - 1:
            assert _reply_state(lib, b) == (1, REPLY_STEP * (k + 1))
    lines = b.lines()
    assert [ln[:3] for ln in lines] == [b"$D,"] * steps + [b"$S,"]  # each sample's D frame first, then S whole
    assert lines[-1] + b"\n" == want and _reply_state(lib, b)[0] == 0
    # a board whose sensor is silent: the idle loop answers
    lib.fw_uart_rx(b.mem, request, len(request))
    assert b.out == b""
    lib.fw_board_idle(b.mem)
    assert bytes(b.out) == want
    b.out.clear()
    # two commands in one read, no sample, no idle pass between them: S first, then the identity
    both = request + sf.encode("CALR") + sf.encode("ID")
    lib.fw_uart_rx(b.mem, both, len(both))
    lib.fw_board_idle(b.mem)
    got = b.frames()
    assert [type(f) for f in got] == [sf.SfemReadFrame, sf.CalReadFrame, sf.IdentityFrame]
    assert got[0].encode() == want and got[1] == _calr(thermal, False, b.slots)
    # decimated: the samples the decimation drops step the reply too
    assert b.cmd("ODR,0.625")[0].command == "ODR"
    lib.fw_uart_rx(b.mem, request, len(request))
    for k in range(steps):
        b.sample([k, 0, 16000], 25)
    assert [ln[:3] for ln in b.lines()] == [b"$D,", b"$S,"]


# ---- the board on a fake HAL: CAN (design 3.2) ----------------------------------------------------

def _sim_can(node, ident, thermal=None, comp=False):
    from drivers.sim.slcan_pty import SimCanBoard
    sent: list[tuple[int, bytes]] = []
    sim = SimCanBoard(node, ident, send=lambda arb, data: sent.append((arb, bytes(data))))
    if thermal is not None:
        sim.cal.nvm.thermal = thermal
    sim.cal.nvm.comp = comp
    return sim, sent


@pytest.mark.parametrize("ident", [LIS, ADXL, _ident_with(LIS, serial="ABCDEFGHIJKLMN"),
                                   _ident_with(LIS, serial="F4" + "0123456789ABCDEF01234567")])
def test_can_identity_and_samples_match_sim(lib, ident):
    node = 5
    b = Board(lib, ident, can_node=node)
    assert b.out == b""
    ug = C.c_float()
    shift = lib.fw_can_scale(C.byref(b.id), C.byref(ug))
    assert (shift, ug.value) == (can_scale(ident)[0], cf.float32(can_scale(ident)[1]))
    got = b.can_cmd(node, cf.encode_command(cf.CMD_IDENTIFY))
    # the simulated CAN board keeps design 3.2's 14-character serial: frames 0 and 1 are the same
    sim_ident = _ident_with(ident, serial=ident.serial[:14])
    sim, sent = _sim_can(node, sim_ident)
    sim.on_frame(cf.CMD_BASE + node, cf.encode_command(cf.CMD_IDENTIFY))
    # frames 0..3 byte for byte what the simulated CAN board sends (it knows no more), then frame 11
    # and, for a serial longer than 14 (an STM32's F4 + 24 hex digits), frames 12 and 13
    long_serial = len(ident.serial) > 14
    assert [d[0] for _, d in got] == [0, 1, 2, 3, 11] + ([12, 13] if long_serial else [])
    assert {arb for arb, _ in got} == {cf.IDENT_BASE + node}
    assert got[:4] == sent
    # frame 11 of a board never told its reset cause, on erased flash
    assert cf.decode_identity_health(got[4][1]) == ("unknown", BoardRecordInfo(0, 0, None, "empty"))
    asm = cf.IdentityAssembler()
    for _, d in got:
        asm.feed(d)
    assert asm.complete and asm.serial == ident.serial
    assert asm.waits_for_more == (len(ident.serial) == 14)  # only 14 characters are ambiguous (12/13 may follow)
    assert b.can_cmd(node + 1, cf.encode_command(cf.CMD_IDENTIFY)) == []  # another node's command
    rng = np.random.default_rng(13)
    fs = 32767 if ident is not ADXL else 524287
    for comp in (False, True):
        thermal = _coefficients(rng, False)[0] if comp else None
        b = Board(lib, ident, can_node=node)
        if comp:
            for k, v in enumerate(thermal):
                b.can_cmd(node, cf.encode_cal_field(k, v))
            assert b.can_cmd(node, cf.encode_cal_commit(crc32_f32(thermal)))[0][1][1] == cf.CAL_STORED
            assert b.can_cmd(node, cf.encode_comp(True)) == []  # COMP: no reply in 3.2
        sim, sent = _sim_can(node, sim_ident, thermal, comp)
        for cmd in (cf.encode_command(cf.CMD_SET_ODR, 0.625), cf.encode_command(cf.CMD_START)):
            assert b.can_cmd(node, cmd) == []
            sim.on_frame(cf.CMD_BASE + node, cmd)
        n = 600
        acc = rng.integers(-fs, fs + 1, (n, 3))
        acc[:5] = [[fs, fs, fs], [-fs - 1, -fs - 1, -fs - 1], [8, -8, 7], [-9, 9, 24], [0, 0, 0]]
        tcounts = np.rint(ident.t_lsb_at_25c + rng.uniform(-60, 60, n) * ident.t_lsb_per_c).astype(np.int64)
        for k in range(n):
            b.sample(acc[k].tolist(), int(tcounts[k]))
        sim.feed(np.arange(n) / 3.125, acc, tcounts)
        got = b.can
        assert [a for a, _ in got] == [cf.SAMPLE_BASE + node] * (n // 5) == [a for a, _ in sent]
        g = [cf.decode_sample(d) for _, d in got]
        w = [cf.decode_sample(d) for _, d in sent]
        assert [(x.t, x.seq) for x in g] == [(x.t, x.seq) for x in w]
        diff = np.abs(np.array([[x.ax, x.ay, x.az] for x in g]) - np.array([[x.ax, x.ay, x.az] for x in w]))
        if comp:
            assert diff.max() <= 1 and (diff == 0).mean() > 0.95
        else:
            assert diff.max() == 0  # raw counts: bit-exact, shift rounding included


def test_can_calibration_write_back(lib):
    node = 9
    b = Board(lib, ADXL, can_node=node)
    vals = to_f32([0.7, -1.1, 0.2, -120.5, -310.0, -5.25])
    for k, v in enumerate(vals):
        assert b.can_cmd(node, cf.encode_cal_field(k, v)) == []
    ((arb, st),) = b.can_cmd(node, cf.encode_cal_commit(crc32_f32(vals) ^ 1))
    assert arb == cf.IDENT_BASE + node and cf.decode_cal_reply(st)[1].status == cf.CAL_CRC_MISMATCH
    for k, v in enumerate(vals[:5]):  # a field missing: mismatch, nothing stored
        b.can_cmd(node, cf.encode_cal_field(k, v))
    assert cf.decode_cal_reply(b.can_cmd(node, cf.encode_cal_commit(crc32_f32(vals)))[0][1])[1].status == 1
    assert b.writes == []
    for k, v in enumerate(vals):
        b.can_cmd(node, cf.encode_cal_field(k, v))
    ((_, st),) = b.can_cmd(node, cf.encode_cal_commit(crc32_f32(vals)))
    assert cf.decode_cal_reply(st) == (4, cf.CalStatus(cf.CAL_STORED, False, crc32_f32(vals)))
    b.can_cmd(node, cf.encode_comp(True))
    got = b.can_cmd(node, cf.encode_cal_read())
    assert [d[0] for _, d in got] == [5, 6, 7, 8, 9, 10, 4]
    sim, sent = _sim_can(node, ADXL, vals, True)
    sim.on_frame(cf.CMD_BASE + node, cf.encode_cal_read())
    assert got == sent  # byte for byte what the simulated CAN board answers
    b.fail_writes = 1
    for k, v in enumerate(vals):
        b.can_cmd(node, cf.encode_cal_field(k, v + 1))
    ((_, st),) = b.can_cmd(node, cf.encode_cal_commit(crc32_f32([v + 1 for v in vals])))
    assert cf.decode_cal_reply(st)[1] == cf.CalStatus(cf.CAL_WRITE_FAILED, True, crc32_f32(vals))
    b2 = Board(lib, ADXL, can_node=node, slots=b.slots)  # power cycle: no serial E frame on CAN
    assert b2.out == b"" and b2.can == []
    got = b2.can_cmd(node, cf.encode_cal_read())
    assert [cf.decode_cal_reply(d)[1] for _, d in got[:6]] == list(vals)
    assert cf.decode_cal_reply(got[6][1])[1] == cf.CalStatus(cf.CAL_STORED, True, crc32_f32(vals))
    for junk in (b"", b"\x09", b"\x05\x07\0\0\0\0", b"\x04\x00", b"\x08\x02"):
        before = b2.head.rx_bad_frames
        assert b2.can_cmd(node, junk) == []
        assert b2.head.rx_bad_frames == before + 1, junk


def test_core_compiles_for_cortex_m4f():
    """The core builds for the M4F (single-precision FPU, newlib-nano) with the same warnings."""
    if missing_tools("disc"):
        pytest.skip("arm-none-eabi-gcc not installed")
    objs = sorted(p.name for p in build("core-arm").rglob("*.o"))  # make under the build lock; raises on error
    assert "fw_num.o" in objs and "fw_board.o" in objs
