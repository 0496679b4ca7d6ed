"""Issue 42 in the board firmware's core: identity keys, calibration records, sample counting.

docs/design.md 3.1 is the truth checked here, against independent implementations:
- the identity reply's trailing keys (reset, boots, fault, fault_pc, rec_*, caps, sensor_reinit),
  the same rec_* keys in the C reply, `E,NVM` after `I` while the record state is fallback or
  corrupt, CAN identity frames 11/12/13 (a 26-character STM32 serial: "F4" + the UID in hex);
- every coefficient checked finite on every path: CAN CAL_FIELD/CAL_COMMIT, NVM records at boot
  (built here byte by byte by tests/firmware_nvm.py with every CRC right, so only the finiteness
  check can refuse them), the version-2 record;
- the version-2 record (the cubic thermal SFEM): $SFTW/$SFTC/$SFTR, its NVM layout decoded by
  tests/firmware_nvm.py, and the compensated output against a float64 numpy evaluation of
  sensors2023 eq. 8; version-1 images still boot and apply;
- seq counts samples taken: a t_us gap counts the missed output samples, with or without
  decimation, on serial and CAN, against a model that numbers every source period;
- the calibrator fault hook (fw_board_selfcal_skew) in the R reply of $SCRR.
The C core runs in-process through ctypes (a fake HAL: UART bytes, CAN frames, two NVM slots as
bytearrays) and as real fwboard processes on ptys (tests/firmware_proc.py).
"""

from __future__ import annotations

import ctypes as C
import struct
import zlib

import numpy as np
import pytest

from contracts.types import Identity
from drivers.protocol import can_frames as cf
from drivers.protocol import serial_frames as sf
from drivers.protocol.cal_record import crc32_f32, to_f32
from drivers.protocol.slcan_lines import split_frames
from drivers.sim.board_nvm import CalFirmware
from drivers.sim.firmware_build import build, missing_tools
from tests.firmware_ctypes import header_define
from tests.firmware_ctypes import CAN_FN, FwHal, FwIdentity, FwRawSample, NVM_RD, NVM_WR, UART_FN
from tests.firmware_nvm import (RECORD2_BYTES, RECORD_BYTES, SLOT_BYTES, crc_f32, decode_slot, encode_record,
                                slot_image)
from tests.firmware_proc import FwProc, _spawn, bodies, fwboard, procs, split_keys  # noqa: F401 (fixtures)

LIS = Identity("SN0001", "LIS3DSH", "fw-c-1.0", 60.0, 1.0, 0.0, 3.125)
ADXL = Identity("AX0001", "ADXL355", "fw-c-1.0", 3.9, -9.05, 1885.0, 3.125)
PERIOD_US = 320_000  # 3.125 Hz
RESET_POWER, RESET_WATCHDOG, RESET_FAULT = 1, 3, 4
IDENTITY_KEYS = ["reset", "boots", "fault", "fault_pc", "rec_ver", "rec_gen", "rec_slot", "rec_state", "caps",
                 "sensor_reinit"]  # the contract's table, in its order
REC_KEYS = ["rec_ver", "rec_gen", "rec_slot", "rec_state"]
F32_EPS = float(np.finfo(np.float32).eps)


assert header_define("fw_hal.h", "FW_NVM_SLOT_BYTES") == SLOT_BYTES  # the layout tests/firmware_nvm.py decodes


class FwCubic(C.Structure):
    _fields_ = [("t_ref_c", C.c_float), ("t_lo_c", C.c_float), ("t_hi_c", C.c_float), ("c", C.c_float * 48),
                ("crc", C.c_uint32), ("present", C.c_uint8)]


class FwBootInfo(C.Structure):
    _fields_ = [("cause", C.c_uint8), ("boots", C.c_uint32), ("fault_cfsr", C.c_uint32), ("fault_pc", C.c_uint32)]


@pytest.fixture(scope="module")
def lib():
    if missing_tools("host"):
        pytest.skip(f"no {missing_tools('host')}")
    so = C.CDLL(str(build("host") / "libfwcore.so"))
    so.fw_board_sizeof.restype = C.c_uint32
    so.fw_board_init.argtypes = [C.c_void_p, C.POINTER(FwHal), C.POINTER(FwIdentity), C.c_uint8]
    so.fw_uart_rx.argtypes = [C.c_void_p, C.c_char_p, C.c_uint32]
    so.fw_board_idle.argtypes = [C.c_void_p]
    so.fw_layout.argtypes = [C.c_char_p]
    so.fw_layout.restype = C.c_uint32
    # the mirrors above are the C structs (a mismatch would read garbage, not fail): checked by name
    for cname, mirror in (("fw_identity_t", FwIdentity), ("fw_cubic_t", FwCubic), ("fw_boot_info_t", FwBootInfo),
                          ("fw_raw_sample_t", FwRawSample), ("fw_hal_t", FwHal)):
        assert C.sizeof(mirror) == so.fw_layout(cname.encode()), cname
        for fname, _ in mirror._fields_:
            off = so.fw_layout(f"{cname}.{fname}".encode())
            assert off == getattr(mirror, fname).offset or (off == 0xFFFFFFFF and cname in ("fw_raw_sample_t", "fw_hal_t")), \
                (cname, fname)
    so.fw_can_rx.argtypes = [C.c_void_p, C.c_uint16, C.c_uint8, C.c_char_p]
    so.fw_sample.argtypes = [C.c_void_p, C.POINTER(FwRawSample)]
    so.fw_board_set_boot.argtypes = [C.c_void_p, C.POINTER(FwBootInfo)]
    so.fw_board_sensor_reinit.argtypes = [C.c_void_p, C.c_uint32]
    so.fw_board_selfcal_skew.argtypes = [C.c_void_p, C.c_float]
    so.fw_serial_from_uid.argtypes = [C.c_char_p, C.c_char_p]
    so.fw_serial_from_uid.restype = C.c_uint32
    so.fw_compensate_cubic_f32.argtypes = [C.POINTER(FwCubic), C.c_float, C.POINTER(C.c_int32), C.c_float,
                                           C.POINTER(C.c_float)]
    so.fw_cubic_crc.argtypes = [C.POINTER(FwCubic)]
    so.fw_cubic_crc.restype = C.c_uint32
    return so


def c_identity(i: Identity) -> FwIdentity:
    return FwIdentity(i.serial.encode(), i.sensor.encode(), i.fw.encode(), i.ug_per_lsb, i.t_lsb_per_c,
                      i.t_lsb_at_25c, i.odr_hz)


class Board:
    """One board on a fake HAL: `out` the serial bytes sent, `can` the CAN frames, `slots` the flash."""

    def __init__(self, lib, ident: Identity = LIS, can_node: int = 0, slots=None) -> None:
        self.lib = lib
        self.out = bytearray()
        self.can: list[tuple[int, bytes]] = []
        self.slots = slots if slots is not None else [bytearray(b"\xff" * SLOT_BYTES) for _ in range(2)]
        self.writes: list[int] = []
        self._cbs = (UART_FN(self._uart), CAN_FN(self._can), NVM_RD(self._rd), NVM_WR(self._wr))
        self.hal = FwHal(None, self._cbs[0] if not can_node else UART_FN(), self._cbs[1] if can_node else CAN_FN(),
                         self._cbs[2], self._cbs[3])
        self.mem = C.create_string_buffer(lib.fw_board_sizeof())
        self.id = c_identity(ident)
        self.node = can_node
        lib.fw_board_init(self.mem, C.byref(self.hal), C.byref(self.id), can_node)

    def _uart(self, ctx, buf, n):
        self.out += C.string_at(buf, n)

    def _can(self, ctx, arb, dlc, data):
        self.can.append((arb, C.string_at(data, dlc)))

    def _rd(self, ctx, slot, buf, n):
        assert n <= SLOT_BYTES
        C.memmove(buf, bytes(self.slots[slot][:n]), n)
        return 0

    def _wr(self, ctx, slot, buf, n):
        self.writes.append(slot)
        self.slots[slot][:] = C.string_at(buf, n) + b"\xff" * (SLOT_BYTES - n)
        return 0

    def set_boot(self, cause: int, boots: int, cfsr: int = 0, pc: int = 0) -> None:
        info = FwBootInfo(cause, boots, cfsr, pc)
        self.lib.fw_board_set_boot(self.mem, C.byref(info))

    def take(self) -> list[list[str]]:
        """The frames sent since the last take, as fields (checksums verified)."""
        raw = bytes(self.out)
        self.out.clear()
        return bodies(raw)

    def cmd(self, body: str) -> list[list[str]]:
        self.lib.fw_uart_rx(self.mem, sf.encode(body), len(sf.encode(body)))
        self.lib.fw_board_idle(self.mem)   # the target's idle pass: a long reply goes out
        return self.take()

    def ident(self) -> tuple[list[str], dict[str, str], list[list[str]]]:
        """ID: the identity's base fields, its keys, and the frames after it."""
        got = self.cmd("ID")
        assert got and got[0][0] == "I", got
        base, keys = split_keys(got[0])
        return base, keys, got[1:]

    def sample(self, t_us: int, acc, temp: int) -> None:
        s = FwRawSample(t_us & 0xFFFFFFFF, (C.c_int32 * 3)(*[int(v) for v in acc]), int(temp))
        self.lib.fw_sample(self.mem, C.byref(s))

    def can_cmd(self, data: bytes) -> list[tuple[int, bytes]]:
        self.lib.fw_can_rx(self.mem, cf.CMD_BASE + self.node, len(data), data)
        got, self.can = self.can, []
        return got


def _calw(b: Board, thermal) -> list[list[str]]:
    return b.cmd(sf.cmd_calw(thermal[:3], thermal[3:])[1:-4].decode())


def _f32(text: str) -> float:
    return float(np.float32(float(text)))


# ---- identity keys ----------------------------------------------------------------------------------

def test_identity_keys_follow_the_contract(lib):
    b = Board(lib, LIS)
    b.set_boot(RESET_POWER, 1)
    base, keys, after = b.ident()
    old = sf.IdentityFrame(LIS).encode()[1:-4].decode().split(",")
    assert base == old  # the base fields are exactly those of design 3.1
    assert keys == {"reset": "power", "boots": "1", "rec_ver": "0", "rec_gen": "0", "rec_slot": "-",
                    "rec_state": "empty", "caps": "scal+sfem3", "sensor_reinit": "0"}
    assert list(keys) == [k for k in IDENTITY_KEYS if k in keys] and after == []
    # a start after a fault: the stored CFSR and the stacked PC, 8 upper-case hex digits each
    b.set_boot(RESET_FAULT, 3, 0x00010000, 0x0800ABCD)
    _, keys, _ = b.ident()
    assert (keys["reset"], keys["boots"], keys["fault"], keys["fault_pc"]) == ("fault", "3", "00010000", "0800ABCD")
    assert list(keys) == [k for k in IDENTITY_KEYS if k in keys]
    b.set_boot(RESET_WATCHDOG, 4, 0x1234, 0x5678)  # fault words only after reset=fault
    _, keys, _ = b.ident()
    assert keys["reset"] == "watchdog" and "fault" not in keys and "fault_pc" not in keys
    # the target re-initialised a silent sensor: E,SENSOR now, counted in the identity
    b.lib.fw_board_sensor_reinit(b.mem, 1234)
    (err,) = b.take()
    assert err[:2] == ["E", "SENSOR"] and "1234" in err[2]
    _, keys, _ = b.ident()
    assert keys["sensor_reinit"] == "1"
    # a record written: version 1, generation 1 in slot 0; the C reply carries the same keys
    thermal = to_f32([0.5, -0.5, 0.25, -100, -200, -300])
    assert _calw(b, thermal)[0][:2] == ["A", "CALW"]
    _, keys, _ = b.ident()
    assert [keys[k] for k in REC_KEYS] == ["1", "1", "0", "ok"]
    (c,) = b.cmd("CALR")
    cbase, ckeys = split_keys(c)
    assert sf.FrameParser().feed(sf.encode(",".join(cbase))) == [sf.CalReadFrame(thermal, crc32_f32(thermal), False)]
    assert list(ckeys) == REC_KEYS and ckeys == {k: keys[k] for k in REC_KEYS}


def test_can_identity_frames_11_12_13(lib):
    uid = bytes(range(0x10, 0x1C))
    out = C.create_string_buffer(32)
    assert lib.fw_serial_from_uid(uid, out) == 26
    serial = out.value.decode()
    assert serial == "F4" + uid.hex().upper()  # design 3.1: F4 + the 96-bit UID, byte 0 first
    node = 9
    b = Board(lib, Identity(serial, "LIS3DSH", "fw-c-1.0", 60.0, 1.0, 0.0, 3.125), can_node=node)
    b.set_boot(RESET_WATCHDOG, 2)
    got = b.can_cmd(cf.encode_command(cf.CMD_IDENTIFY))
    assert [a for a, _ in got] == [cf.IDENT_BASE + node] * 7
    data = {d[0]: d for _, d in got}
    assert [d[0] for _, d in got] == [0, 1, 2, 3, 11, 12, 13]  # the additions after the four of 3.2
    joined = b"".join(data[k][1:8] for k in (0, 1, 12, 13))
    assert joined.rstrip(b"\0").decode() == serial and len(joined) == 28
    assert data[11] == bytes([11, RESET_WATCHDOG, 2, 0]) + struct.pack("<I", 0)  # empty, no record
    vals = to_f32([0.7, -1.1, 0.2, -120.5, -310.0, -5.25])
    for k, v in enumerate(vals):
        b.can_cmd(cf.encode_cal_field(k, v))
    assert cf.decode_cal_reply(b.can_cmd(cf.encode_cal_commit(crc32_f32(vals)))[0][1])[1].status == cf.CAL_STORED
    got = b.can_cmd(cf.encode_command(cf.CMD_IDENTIFY))
    assert got[4][1] == bytes([11, RESET_WATCHDOG, 0, 1]) + struct.pack("<I", 1)  # ok, version 1, generation 1
    # a 14-character serial: the four frames of 3.2 and frame 11, no 12/13
    b = Board(lib, Identity("ABCDEFGHIJKLMN", "LIS3DSH", "fw-c-1.0", 60.0, 1.0, 0.0, 3.125), can_node=node)
    assert [d[0] for _, d in b.can_cmd(cf.encode_command(cf.CMD_IDENTIFY))] == [0, 1, 2, 3, 11]
    # the serial board sends the whole 26 characters in its I frame
    s = Board(lib, Identity(serial, "LIS3DSH", "fw-c-1.0", 60.0, 1.0, 0.0, 3.125))
    assert s.ident()[0][1] == serial


# ---- finite coefficients on every path ------------------------------------------------------------

NAN_BITS = [0x7FC00000, 0x7F800001, 0xFFC00000, 0x7F800000, 0xFF800000]  # NaNs (quiet, signalling), +-inf


@pytest.mark.parametrize("bits", NAN_BITS)
def test_can_commit_refuses_non_finite_fields(lib, bits):
    node = 5
    b = Board(lib, ADXL, can_node=node)
    good = to_f32([0.7, -1.1, 0.2, -120.5, -310.0, -5.25])
    raw = [struct.pack("<f", v) for v in good]
    raw[3] = struct.pack("<I", bits)
    for k, r in enumerate(raw):
        assert b.can_cmd(bytes([cf.CMD_CAL_FIELD, k]) + r) == []
    crc = zlib.crc32(b"".join(raw))  # the CRC of exactly the bytes sent: only the value check can refuse
    ((_, st),) = b.can_cmd(cf.encode_cal_commit(crc))
    assert cf.decode_cal_reply(st)[1].status == cf.CAL_CRC_MISMATCH and b.writes == []
    got = b.can_cmd(cf.encode_cal_read())
    assert [cf.decode_cal_reply(d)[1] for _, d in got[:6]] == [0.0] * 6
    for k, v in enumerate(good):  # the same board takes finite values at once
        b.can_cmd(cf.encode_cal_field(k, v))
    ((_, st),) = b.can_cmd(cf.encode_cal_commit(crc32_f32(good)))
    assert cf.decode_cal_reply(st)[1].status == cf.CAL_STORED and b.writes == [0]


GOOD_THERMAL = to_f32([0.5, -0.5, 0.25, -100, -200, -300])
GOOD_SFEM = to_f32([1.001, 0.002, -0.001, 0.0005, 0.998, 0.003, -0.002, 0.001, 1.0004, 0.012, -0.008, 0.02])


def _cubic_values(rng, t_ref=25.0, t_lo=-10.0, t_hi=70.0) -> tuple[float, ...]:
    """51 float32 values in the $SFTC order: a plausible cubic SFEM (A near I, b near 0 g)."""
    c = np.zeros((4, 12))
    c[0, :9] = np.eye(3).reshape(-1) + rng.normal(0, 2e-3, 9)
    c[0, 9:] = rng.normal(0, 0.02, 3)
    for k, scale_a, scale_b in ((1, 1e-4, 2e-4), (2, 1e-6, 3e-6), (3, 1e-8, 4e-8)):
        c[k, :9] = rng.normal(0, scale_a, 9)
        c[k, 9:] = rng.normal(0, scale_b, 3)
    return to_f32([t_ref, t_lo, t_hi, *c.reshape(-1)])


BAD_RECORDS = {
    "thermal NaN": dict(thermal=[*GOOD_THERMAL[:2], float("nan"), *GOOD_THERMAL[3:]]),
    "sfem inf": dict(sfem=[*GOOD_SFEM[:10], float("inf"), GOOD_SFEM[11]]),
    "cubic NaN": dict(cubic=("nan", 20)),
    "cubic t_hi inf": dict(cubic=("inf", 2)),
}


def _bad_record(kind: str, generation: int) -> bytes:
    spec = BAD_RECORDS[kind]
    thermal = spec.get("thermal", GOOD_THERMAL)
    sfem = spec.get("sfem", GOOD_SFEM)
    cubic = None
    if "cubic" in spec:
        word, index = spec["cubic"]
        cubic = list(_cubic_values(np.random.default_rng(3)))
        cubic[index] = float(word)
    return encode_record(generation, thermal, sfem, True, cubic)


@pytest.mark.parametrize("kind", list(BAD_RECORDS))
def test_nvm_record_with_a_non_finite_value_is_never_applied(lib, kind):
    bad = _bad_record(kind, 5)
    assert decode_slot(0, slot_image(bad)) is None  # every CRC right, yet not a valid record
    # the only record: CORRUPT, zeros, compensation off, reported at boot and after every ID
    b = Board(lib, LIS, slots=[bytearray(slot_image(bad)), bytearray(slot_image(None))])
    msg = ["E", "NVM", "calibration record with a non-finite value in slot 0"]
    assert b.take() == [msg]
    base, keys, after = b.ident()
    assert [keys[k] for k in REC_KEYS] == ["0", "0", "-", "corrupt"] and after == [msg]
    assert b.cmd("CALR") == [["E", "CALR", "calibration record corrupt"]]
    b.cmd("START")
    b.sample(0, [1000, -1000, 16000], 40)
    assert b.take() == [["D", "0", "0", "1000", "-1000", "16000", "40"]]  # raw counts
    # newer and bad over an older good one: the older applies, state fallback
    good = encode_record(4, GOOD_THERMAL, GOOD_SFEM, True)
    b = Board(lib, LIS, slots=[bytearray(slot_image(good)), bytearray(slot_image(bad))])
    msg1 = ["E", "NVM", "calibration record with a non-finite value in slot 1"]
    assert b.take() == [msg1]
    _, keys, after = b.ident()
    assert [keys[k] for k in REC_KEYS] == ["1", "4", "0", "fallback"] and after == [msg1]
    (c,) = b.cmd("CALR")
    assert tuple(_f32(v) for v in c[1:7]) == GOOD_THERMAL and c[8] == "1"


def test_torn_newer_slot_is_a_fallback_until_the_next_write(lib):
    b = Board(lib, LIS)
    first, second, third = (to_f32([k, -k, 0.5 * k, -10 * k, -20 * k, -30 * k]) for k in (1, 2, 3))
    _calw(b, first)
    _calw(b, second)
    assert b.writes == [0, 1]
    slots = [bytearray(s) for s in b.slots]
    slots[1][60:] = b"\xff" * (SLOT_BYTES - 60)  # the write of generation 2 torn after 60 bytes
    b2 = Board(lib, LIS, slots=slots)
    msg = ["E", "NVM", "calibration record CRC mismatch in slot 1"]
    assert b2.take() == [msg]
    _, keys, after = b2.ident()
    assert [keys[k] for k in REC_KEYS] == ["1", "1", "0", "fallback"] and after == [msg]
    (c,) = b2.cmd("CALR")
    assert tuple(_f32(v) for v in c[1:7]) == first and split_keys(c)[1]["rec_state"] == "fallback"
    _calw(b2, third)  # over the torn slot, never over the good one
    assert b2.writes == [1]
    _, keys, after = b2.ident()
    assert [keys[k] for k in REC_KEYS] == ["1", "2", "1", "ok"] and after == []
    # a rotten byte (not a torn write) in the newer slot reads the same way
    slots = [bytearray(s) for s in b2.slots]
    slots[1][20] ^= 0x04
    b3 = Board(lib, LIS, slots=slots)
    assert b3.take() == [msg]
    _, keys, after = b3.ident()
    assert keys["rec_state"] == "fallback" and keys["rec_slot"] == "0" and after == [msg]


# ---- the version-2 record: cubic SFEM ----------------------------------------------------------------

def _stage_and_commit(b: Board, vals, crc: int | None = None) -> list[list[str]]:
    c = np.array(vals[3:]).reshape(4, 12)
    for k in range(4):
        body = "SFTW," + str(k) + "," + ",".join(sf.fmt_f32(v) for v in c[k])
        assert b.cmd(body) == [["A", "SFTW", str(k)]]
    crc = crc_f32(vals) if crc is None else crc
    return b.cmd("SFTC," + ",".join(sf.fmt_f32(v) for v in vals[:3]) + "," + sf.fmt_crc(crc))


def _read_cubic(b: Board) -> tuple[float, ...]:
    (h,) = b.cmd("SFTR,H")
    assert h[:2] == ["T", "H"] and len(h) == 6
    vals = [_f32(v) for v in h[2:5]]
    for k in range(4):
        (t,) = b.cmd(f"SFTR,{k}")
        assert t[:2] == ["T", str(k)] and len(t) == 14
        vals += [_f32(v) for v in t[2:]]
    assert int(h[5], 16) == crc_f32(vals)
    return tuple(vals)


def test_cubic_record_write_read_back_and_layout(lib):
    rng = np.random.default_rng(42)
    vals = _cubic_values(rng)
    b = Board(lib, ADXL)
    assert b.cmd("SFTR,H") == [["E", "SFTR", "no cubic SFEM stored"]]
    _calw(b, GOOD_THERMAL)
    a, bb = np.array(GOOD_SFEM[:9]).reshape(3, 3), GOOD_SFEM[9:]
    assert b.cmd(sf.cmd_sfew(a, bb)[1:-4].decode())[0][:2] == ["A", "SFEW"]
    assert _stage_and_commit(b, vals) == [["A", "SFTC", sf.fmt_crc(crc_f32(vals))]]
    rec = decode_slot(0, bytes(b.slots[b.writes[-1]]))
    assert rec is not None and rec.version == 2 and rec.generation == 3 and rec.cubic == vals
    assert rec.thermal == GOOD_THERMAL and rec.sfem == GOOD_SFEM  # version 1's part kept
    assert bytes(b.slots[b.writes[-1]][RECORD2_BYTES:]) == b"\xff" * (SLOT_BYTES - RECORD2_BYTES)
    assert _read_cubic(b) == vals
    _, keys, _ = b.ident()
    assert [keys[k] for k in REC_KEYS] == ["2", "3", "0", "ok"]
    # CALW, SFEW and COMP on a version-2 board keep the cubic part (version 2 written again)
    new_thermal = to_f32([1, 2, 3, -4, -5, -6])
    _calw(b, new_thermal)
    b.cmd("COMP,1")
    rec = decode_slot(0, bytes(b.slots[b.writes[-1]]))
    assert rec.version == 2 and rec.cubic == vals and rec.thermal == new_thermal and rec.comp and rec.generation == 5
    (s,) = b.cmd("SFER")
    assert tuple(_f32(v) for v in s[1:13]) == GOOD_SFEM
    # power cycle: the version-2 record applies
    b2 = Board(lib, ADXL, slots=b.slots)
    assert b2.take() == [] and _read_cubic(b2) == vals
    _, keys, _ = b2.ident()
    assert [keys[k] for k in REC_KEYS] == ["2", "5", "0", "ok"]


def test_cubic_commit_checks(lib):
    rng = np.random.default_rng(7)
    vals = _cubic_values(rng)
    b = Board(lib, LIS)
    head = ",".join(sf.fmt_f32(v) for v in vals[:3])
    c = np.array(vals[3:]).reshape(4, 12)
    row = [",".join(sf.fmt_f32(v) for v in c[k]) for k in range(4)]
    for k in range(3):  # power 3 never staged
        b.cmd(f"SFTW,{k},{row[k]}")
    assert b.cmd(f"SFTC,{head},{sf.fmt_crc(crc_f32(vals))}") == [["E", "SFTC", "not all 4 powers staged"]]
    for k in range(4):
        b.cmd(f"SFTW,{k},{row[k]}")
    # every $SFTC ends the staging: after one refused, the four must come again
    assert b.cmd(f"SFTC,{head},{sf.fmt_crc(crc_f32(vals) ^ 1)}")[0][:3] == ["E", "SFTC", f"crc mismatch: board computed {sf.fmt_crc(crc_f32(vals))}"]
    assert b.cmd(f"SFTC,{head},{sf.fmt_crc(crc_f32(vals))}") == [["E", "SFTC", "not all 4 powers staged"]]
    errors = {
        f"SFTW,4,{row[0]}": "SFTW", f"SFTW,0,{row[0]},1": "SFTW", "SFTW,0," + ",".join(["1"] * 11) + ",nan": "SFTW",
        "SFTW,1," + ",".join(["1"] * 11) + ",-inf": "SFTW", "SFTW,x," + row[0]: "SFTW",
        "SFTR": "SFTR", "SFTR,4": "SFTR", "SFTR,h": "SFTR", "SFTC,25,-10,70": "SFTC",
        f"SFTC,nan,-10,70,{sf.fmt_crc(0)}": "SFTC", "SFTC,25,-10,70,XYZ": "SFTC",
    }
    for body, code in errors.items():
        got = b.cmd(body)
        assert len(got) == 1 and got[0][:2] == ["E", code] and got[0][2], body
    for lo, hi in ((70.0, -10.0), (20.0, 20.0)):  # t_lo_c must lie below t_hi_c
        v = to_f32([25.0, lo, hi, *vals[3:]])
        assert _stage_and_commit(b, v) == [["E", "SFTC", "t_lo_c not below t_hi_c"]]
    assert b.writes == []  # nothing was stored
    assert _stage_and_commit(b, vals)[0][:2] == ["A", "SFTC"] and b.writes == [0]
    # a board whose record is corrupt refuses the commit and the read-back
    slots = [bytearray(b"\x00" * SLOT_BYTES), bytearray(b"\xff" * SLOT_BYTES)]
    bc = Board(lib, LIS, slots=slots)
    bc.take()
    assert _stage_and_commit(bc, vals) == [["E", "SFTC", "calibration record corrupt"]]
    assert bc.cmd("SFTR,H") == [["E", "SFTR", "calibration record corrupt"]]


def cubic_reference(vals, raw, temp_c, ug_per_lsb: float) -> np.ndarray:
    """sensors2023 eq. 8 in float64, written from the contract: T clamped to [t_lo, t_hi],
    d = T - t_ref, A(d)_ij = sum_k c[k][3i+j] d^k, b(d)_i = sum_k c[k][9+i] d^k (g),
    out = A(d) (raw - b(d) / lsb) in counts."""
    t_ref, t_lo, t_hi = vals[:3]
    c = np.asarray(vals[3:], dtype=np.float64).reshape(4, 12)
    d = np.clip(np.asarray(temp_c, dtype=np.float64), t_lo, t_hi) - t_ref
    powers = np.stack([d ** k for k in range(4)], axis=1)  # (n, 4)
    m = powers @ c  # (n, 12)
    a = m[:, :9].reshape(-1, 3, 3)
    b_counts = m[:, 9:] / (ug_per_lsb * 1e-6)
    w = np.asarray(raw, dtype=np.float64) - b_counts
    return np.einsum("nij,nj->ni", a, w), np.einsum("nij,nj->ni", np.abs(a), np.abs(w) + np.abs(b_counts))


ULPS_TOL = 4  # float32 ulps of the summed terms |A||raw - b|: measured <= 1.83 over 3000 samples per sensor


def _gravity_counts(rng, ident: Identity, n: int) -> np.ndarray:
    """Raw counts a sensor reads at rest: 0.8-1.2 g in a random direction."""
    v = rng.normal(0, 1, (n, 3))
    v *= (rng.uniform(0.8, 1.2, n) / np.linalg.norm(v, axis=1))[:, None]
    return np.rint(v * 1e6 / ident.ug_per_lsb).astype(np.int64)


def _cubic_struct(vals) -> FwCubic:
    cu = FwCubic()
    cu.t_ref_c, cu.t_lo_c, cu.t_hi_c = vals[:3]
    for i, v in enumerate(vals[3:]):
        cu.c[i] = v
    cu.present = 1
    return cu


@pytest.mark.parametrize("ident", [LIS, ADXL])
def test_cubic_compensation_matches_numpy(lib, ident):
    """fw_compensate_cubic_f32 against the float64 model: within a few float32 ulps of the terms
    summed (the rounding of the float32 Horner steps and the 3-term products)."""
    rng = np.random.default_rng(5)
    vals = _cubic_values(rng)
    cu = _cubic_struct(vals)
    assert lib.fw_cubic_crc(C.byref(cu)) == crc_f32(vals)
    fs = 32767 if ident is LIS else 524287
    n = 3000
    raw = rng.integers(-fs, fs + 1, (n, 3))
    temp_c = np.float32(rng.uniform(-40, 100, n))  # inside and outside [t_lo, t_hi]
    counts_per_g = np.float32(1e6) / np.float32(ident.ug_per_lsb)
    got = np.zeros((n, 3))
    out = (C.c_float * 3)()
    for k in range(n):
        lib.fw_compensate_cubic_f32(C.byref(cu), float(counts_per_g), (C.c_int32 * 3)(*raw[k].tolist()),
                                    float(temp_c[k]), out)
        got[k] = list(out)
    want, scale = cubic_reference(vals, raw, temp_c, ident.ug_per_lsb)
    err_ulps = np.abs(got - want) / (scale * F32_EPS)
    print(f"{ident.sensor}: max error {err_ulps.max():.3f} ulps of the summed terms, {np.abs(got - want).max():.4g} counts")
    assert err_ulps.max() < ULPS_TOL, err_ulps.max()
    assert np.abs(got - raw).max() > 100  # the model does something


@pytest.mark.parametrize("ident", [LIS, ADXL])
def test_cubic_record_compensates_d_frames(lib, ident):
    """COMP on with a version-2 record: D frames are the cubic model's counts (rounded half to
    even), not eq. 13 on top of it (the thermal coefficients stored are large and would show)."""
    rng = np.random.default_rng(9)
    vals = _cubic_values(rng)
    b = Board(lib, ident)
    _calw(b, to_f32([5.0, -5.0, 5.0, -500, 500, -500]))
    assert _stage_and_commit(b, vals)[0][:2] == ["A", "SFTC"]
    assert b.cmd("COMP,1") == [["A", "COMP"]] and b.cmd("START") == [["A", "START"]]
    n = 400
    raw = _gravity_counts(rng, ident, n)
    tcounts = np.rint(ident.t_lsb_at_25c + rng.uniform(-50, 70, n) * ident.t_lsb_per_c).astype(np.int64)
    for k in range(n):
        b.sample(k * PERIOD_US, raw[k], tcounts[k])
    got = np.array([[int(v) for v in f[3:6]] for f in b.take()])
    temp_c = np.float32(25) + (tcounts.astype(np.float32) - np.float32(ident.t_lsb_at_25c)) / np.float32(ident.t_lsb_per_c)
    want, scale = cubic_reference(vals, raw, temp_c, ident.ug_per_lsb)
    tol = ULPS_TOL * F32_EPS * scale
    clear = np.abs(np.abs(want - np.floor(want)) - 0.5) > tol  # not within the tolerance of a rounding tie
    assert clear.mean() > 0.5
    np.testing.assert_array_equal(got[clear], np.rint(want)[clear])
    assert np.all(np.abs(got - want) <= 0.5 + tol)


def test_version1_image_boots_applies_and_upgrades(lib):
    """A version-1 record as older firmware wrote it (built here from the layout) boots and
    applies as before; a cubic commit then writes version 2 keeping the thermal part and SFEM."""
    image = encode_record(7, GOOD_THERMAL, GOOD_SFEM, True)
    assert len(image) == RECORD_BYTES
    b = Board(lib, ADXL, slots=[bytearray(slot_image(image)), bytearray(slot_image(None))])
    assert b.take() == []
    _, keys, _ = b.ident()
    assert [keys[k] for k in REC_KEYS] == ["1", "7", "0", "ok"]
    (c,) = b.cmd("CALR")
    assert tuple(_f32(v) for v in c[1:7]) == GOOD_THERMAL and c[8] == "1"
    b.cmd("START")
    rng = np.random.default_rng(4)
    raw = rng.integers(-400000, 400000, (200, 3))
    tc = np.rint(ADXL.t_lsb_at_25c + rng.uniform(-40, 40, 200) * ADXL.t_lsb_per_c).astype(np.int64)
    for k in range(200):
        b.sample(k * PERIOD_US, raw[k], tc[k])
    got = np.array([[int(v) for v in f[3:6]] for f in b.take()])
    fwc = CalFirmware()
    fwc.nvm.thermal, fwc.nvm.sfem = GOOD_THERMAL, GOOD_SFEM
    want = fwc.compensate_counts(raw, ADXL.temp_c(tc), ADXL.ug_per_lsb)  # eq. 13 then the SFEM
    assert np.abs(got - want).max() <= 1 and (got == want).mean() > 0.95
    b.cmd("STOP")
    vals = _cubic_values(rng)
    assert _stage_and_commit(b, vals)[0][:2] == ["A", "SFTC"] and b.writes == [1]
    rec = decode_slot(1, bytes(b.slots[1]))
    assert (rec.version, rec.generation, rec.thermal, rec.sfem, rec.comp, rec.cubic) == \
        (2, 8, GOOD_THERMAL, GOOD_SFEM, True, vals)
    # a version-2 image written here (not by the board) boots too
    image2 = encode_record(11, GOOD_THERMAL, None, False, vals)
    b3 = Board(lib, LIS, slots=[bytearray(slot_image(None)), bytearray(slot_image(image2))])
    assert b3.take() == [] and _read_cubic(b3) == vals
    _, keys, _ = b3.ident()
    assert [keys[k] for k in REC_KEYS] == ["2", "11", "1", "ok"]


# ---- seq: samples taken ------------------------------------------------------------------------------

def _arrivals(rng, n_periods: int, jitter_us: int = 20_000) -> list[tuple[int, int]]:
    """(source period index, t_us) of the samples that arrive: runs of periods with gaps of 1-12
    missed periods between them, each time jittered (the board's data-ready time)."""
    out, k = [], 0
    while k < n_periods:
        run = int(rng.integers(1, 15))
        for j in range(k, min(k + run, n_periods)):
            out.append((j, j * PERIOD_US + int(rng.integers(-jitter_us, jitter_us + 1)) + 10 * PERIOD_US))
        k += run + int(rng.integers(1, 13))
    return out


@pytest.mark.parametrize("decim,can_node", [(1, 0), (5, 0), (3, 0), (1, 4), (5, 4)])
def test_seq_counts_missed_output_samples(lib, decim, can_node):
    """Model: every source period j is numbered; the outputs are the periods with j % decim == 0
    (the phase starts at the first sample after ODR) and an output's seq is how many outputs came
    before it, taken or missed. Frames are sent only for outputs that arrived."""
    rng = np.random.default_rng(decim * 10 + can_node)
    ident = LIS
    b = Board(lib, ident, can_node=can_node)
    if can_node:
        b.can_cmd(cf.encode_command(cf.CMD_SET_ODR, 3.125 / decim))
        b.can_cmd(bytes([cf.CMD_START]))
    else:
        assert b.cmd(f"ODR,{3.125 / decim!r}")[0][:2] == ["A", "ODR"]
        b.cmd("START")
    arrivals = _arrivals(rng, 600)
    for j, t in arrivals:
        b.sample(t, [j, 0, 0], 0)
    expect = [(j // decim, t) for j, t in arrivals if j % decim == 0]
    if can_node:
        got = [cf.decode_sample(d) for _, d in b.can]
        assert [g.seq for g in got] == [s & 0xFF for s, _ in expect]  # the low byte of the same count
        assert [g.ax for g in got] == [j for j, _ in arrivals if j % decim == 0]
    else:
        got = b.take()
        assert [(int(f[1]), int(f[2])) for f in got] == expect
        assert [int(f[3]) for f in got] == [j for j, _ in arrivals if j % decim == 0]
    assert expect[-1][0] > len(expect) + 20  # the run had gaps worth counting


def test_seq_only_counts_while_started_and_never_for_a_clock_going_back(lib):
    b = Board(lib, LIS)
    b.cmd("START")
    for k in range(3):
        b.sample(k * PERIOD_US, [k, 0, 0], 0)
    b.cmd("STOP")
    b.sample(10 * PERIOD_US, [9, 0, 0], 0)  # a gap while stopped: nothing counted
    b.take()
    b.cmd("START")
    b.sample(11 * PERIOD_US, [11, 0, 0], 0)
    b.sample(5 * PERIOD_US, [5, 0, 0], 0)  # the clock went back: no gap of 2^32 - x
    b.sample(6 * PERIOD_US, [6, 0, 0], 0)
    b.sample(6 * PERIOD_US + int(1.4 * PERIOD_US), [7, 0, 0], 0)  # within 1.5 periods: no gap
    b.sample(0xFFFFFFFF - 100_000, [8, 0, 0], 0)  # forward by ~4295 s (more than 2^31 us): not counted
    b.sample(0xFFFFFFFF - 100_000 + PERIOD_US, [9, 0, 0], 0)  # across the 32-bit wrap: one period
    b.sample(0xFFFFFFFF - 100_000 + 3 * PERIOD_US, [10, 0, 0], 0)  # across the wrap: one missed
    assert [(int(f[1]), int(f[3])) for f in b.take()] == [(3, 11), (4, 5), (5, 6), (6, 7), (7, 8), (8, 9),
                                                              (10, 10)]


def test_a_sample_that_could_not_be_sent_still_counts(lib):
    b = Board(lib, LIS)
    b.cmd("START")
    b.sample(0, [1, 0, 0], 0)
    b.hal.uart_write = UART_FN()  # the link cannot take a frame (the core sees no UART)
    b.sample(PERIOD_US, [2, 0, 0], 0)
    b.sample(2 * PERIOD_US, [3, 0, 0], 0)
    b.hal.uart_write = b._cbs[0]
    b.sample(3 * PERIOD_US, [4, 0, 0], 0)
    assert [(int(f[1]), int(f[3])) for f in b.take()] == [(0, 1), (3, 4)]


# ---- the calibrator fault hook ---------------------------------------------------------------------

def _selfcal_run(b: Board, drift_mg_per_c: float) -> None:
    """Two orientations (+-0.577 g on every axis), each at 25 C and 50 C, steady long enough for the
    calibrator to save a segment at each; the offset drifts drift_mg_per_c per C on every axis."""
    lsb_g = ADXL.ug_per_lsb * 1e-6
    t = 0
    for sign, temp in ((1, 25.0), (1, 50.0), (-1, 50.0), (-1, 25.0)):
        acc_g = sign * 0.577 + drift_mg_per_c * 1e-3 * (temp - 25.0)
        counts = int(round(acc_g / lsb_g))
        tc = int(round(ADXL.t_lsb_at_25c + (temp - 25.0) * ADXL.t_lsb_per_c))
        for _ in range(2600):
            b.sample(t, [counts] * 3, tc)
            t += 10_000


def test_scrr_adds_the_calibrator_skew_to_every_tdb(lib):
    b = Board(lib, ADXL)
    assert b.cmd("SCAL,1") == [["A", "SCAL"]]
    _selfcal_run(b, 0.8)
    assert [f[0] for f in b.take()] == ["G"] * 4  # a segment at each plateau
    (r0,) = b.cmd("SCRR")
    assert r0[0] == "R", r0
    tdb0 = [_f32(v) for v in r0[1:4]]
    assert np.allclose(tdb0, 0.8, atol=0.02)  # the calibrator found the drift
    lib.fw_board_selfcal_skew(b.mem, 1.25)
    (r1,) = b.cmd("SCRR")
    assert [_f32(v) for v in r1[1:4]] == [float(np.float32(v) + np.float32(1.25)) for v in tdb0]
    assert r1[4:] == r0[4:]  # TDSF, segments, flags untouched


# ---- real processes ---------------------------------------------------------------------------------

def _p_ident(p: FwProc) -> tuple[list[str], dict[str, str], list[list[str]]]:
    got = p.command_fields("ID", 1)
    got += bodies(p.read_until(lambda b: False, timeout=0.2))  # an E,NVM may follow
    base, keys = split_keys(got[0])
    return base, keys, got[1:]


def test_process_cubic_record_power_cycle_and_output(fwboard, tmp_path, procs):
    rng = np.random.default_rng(17)
    vals = _cubic_values(rng)
    nvm = tmp_path / "nvm.bin"
    p = _spawn(procs, fwboard, ADXL, nvm)
    assert nvm.stat().st_size == 2 * SLOT_BYTES
    c = np.array(vals[3:]).reshape(4, 12)
    for k in range(4):
        assert p.command_fields(f"SFTW,{k}," + ",".join(sf.fmt_f32(v) for v in c[k])) == [["A", "SFTW", str(k)]]
    head = ",".join(sf.fmt_f32(v) for v in vals[:3])
    assert p.command_fields(f"SFTC,{head},{sf.fmt_crc(crc_f32(vals))}") == [["A", "SFTC", sf.fmt_crc(crc_f32(vals))]]
    assert p.command_fields("COMP,1") == [["A", "COMP"]]
    assert p.stop() == 0
    rec = decode_slot(1, nvm.read_bytes()[SLOT_BYTES:])  # generation 2 (COMP) in slot 1
    assert rec is not None and (rec.version, rec.generation, rec.cubic, rec.comp) == (2, 2, vals, True)
    p = _spawn(procs, fwboard, ADXL, nvm)  # power cycle
    _, keys, after = _p_ident(p)
    assert [keys[k] for k in REC_KEYS] == ["2", "2", "1", "ok"] and after == []
    assert p.command_fields("START") == [["A", "START"]]
    n = 150
    raw = _gravity_counts(rng, ADXL, n)
    tc = np.rint(ADXL.t_lsb_at_25c + rng.uniform(-45, 75, n) * ADXL.t_lsb_per_c).astype(np.int64)
    p.feed(raw, tc)
    got = bodies(p.read_until(lambda b: b.count(b"\n") >= n))
    assert [int(f[1]) for f in got] == list(range(n))
    acc = np.array([[int(v) for v in f[3:6]] for f in got])
    temp_c = np.float32(25) + (tc.astype(np.float32) - np.float32(ADXL.t_lsb_at_25c)) / np.float32(ADXL.t_lsb_per_c)
    want, scale = cubic_reference(vals, raw, temp_c, ADXL.ug_per_lsb)
    assert np.all(np.abs(acc - want) <= 0.5 + ULPS_TOL * F32_EPS * scale)
    assert p.stop() == 0


@pytest.mark.parametrize("tear", [60, 200, 311])
def test_process_torn_cubic_write_is_a_fallback(fwboard, tmp_path, procs, tear):
    nvm = tmp_path / "nvm.bin"
    vals = _cubic_values(np.random.default_rng(tear))
    p = _spawn(procs, fwboard, LIS, nvm)
    assert p.command_fields(sf.cmd_calw(GOOD_THERMAL[:3], GOOD_THERMAL[3:])[1:-4].decode())[0][:2] == ["A", "CALW"]
    assert p.stop() == 0
    p = _spawn(procs, fwboard, LIS, nvm, tear=tear)
    c = np.array(vals[3:]).reshape(4, 12)
    for k in range(4):
        assert p.command_fields(f"SFTW,{k}," + ",".join(sf.fmt_f32(v) for v in c[k]))[0][:2] == ["A", "SFTW"]
    p.write(sf.encode("SFTC," + ",".join(sf.fmt_f32(v) for v in vals[:3]) + "," + sf.fmt_crc(crc_f32(vals))))
    assert p.proc.wait(5) != 0  # power lost in the middle of the write: no reply
    p.stop()
    assert decode_slot(1, nvm.read_bytes()[SLOT_BYTES:]) is None
    p = _spawn(procs, fwboard, LIS, nvm)
    msg = ["E", "NVM", "calibration record CRC mismatch in slot 1"]
    assert bodies(p.read_until(lambda b: b"\n" in b)) == [msg]
    _, keys, after = _p_ident(p)
    assert [keys[k] for k in REC_KEYS] == ["1", "1", "0", "fallback"] and after == [msg]
    assert p.command_fields("SFTR,H") == [["E", "SFTR", "no cubic SFEM stored"]]
    assert p.stop() == 0


def test_process_version1_file_and_seq_gap(fwboard, tmp_path, procs):
    """A version-1 NVM file as older firmware left it boots; a t_us gap on the bridge shows as a
    seq gap of exactly the missed output samples."""
    nvm = tmp_path / "nvm.bin"
    nvm.write_bytes(slot_image(encode_record(3, GOOD_THERMAL)) + slot_image(None))
    p = _spawn(procs, fwboard, LIS, nvm)
    _, keys, after = _p_ident(p)
    assert [keys[k] for k in REC_KEYS] == ["1", "3", "0", "ok"] and after == []
    assert p.command_fields("ODR,1.5625") == [["A", "ODR", "1.5625"]]  # decimation 2
    assert p.command_fields("START") == [["A", "START"]]
    t = [k * PERIOD_US for k in range(6)] + [k * PERIOD_US for k in range(13, 20)]  # periods 6..12 missed
    p.feed([[k, 0, 0] for k in range(len(t))], [25] * len(t), t_us=t)
    got = bodies(p.read_until(lambda b: b.count(b"\n") >= 6))
    # outputs at even periods; 6, 8, 10, 12 were missed: seq 3..6 never sent
    assert [(int(f[1]), int(f[2])) for f in got] == [(0, 0), (1, 2 * PERIOD_US), (2, 4 * PERIOD_US),
                                                     (7, 14 * PERIOD_US), (8, 16 * PERIOD_US), (9, 18 * PERIOD_US)]
    assert p.stop() == 0


def test_process_can_refuses_nan_and_sends_frame_11(fwboard, tmp_path, procs):
    node = 3
    p = _spawn(procs, fwboard, ADXL, tmp_path / "can.bin", can=node)

    def exchange(data: bytes, n: int) -> list[tuple[int, bytes]]:
        p.write(b"t%03X%d%s\r" % (cf.CMD_BASE + node, len(data), data.hex().upper().encode()))
        buf = bytearray(p.read_until(lambda b: b.count(b"\r") >= n, timeout=2.0 if n else 0.3))
        frames, garbled = split_frames(buf)
        assert garbled == 0 and not buf
        return frames

    vals = to_f32([0.7, -1.1, 0.2, -120.5, -310.0, -5.25])
    raw = [struct.pack("<f", v) for v in vals]
    raw[0] = struct.pack("<f", float("nan"))
    for k, r in enumerate(raw):
        assert exchange(bytes([cf.CMD_CAL_FIELD, k]) + r, 0) == []
    ((_, st),) = exchange(cf.encode_cal_commit(zlib.crc32(b"".join(raw))), 1)
    assert cf.decode_cal_reply(st)[1].status == cf.CAL_CRC_MISMATCH
    frames = exchange(cf.encode_command(cf.CMD_IDENTIFY), 5)
    assert [d[0] for _, d in frames] == [0, 1, 2, 3, 11]
    assert frames[4][1][2:] == bytes([2, 0]) + struct.pack("<I", 0)  # nothing stored: empty, no version
    assert p.stop() == 0
