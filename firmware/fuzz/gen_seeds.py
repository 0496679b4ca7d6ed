#!/usr/bin/env python3
"""Seed corpora for the four fuzz targets, written from the protocol (design 3.1/3.2, the issue-42
contract docs/design.md 3.1, the NVM layout of core/fw_nvm.h), not from the C code.

Why generated and not committed: the seeds follow the protocol text, so a protocol change is one
edit here instead of a folder of binary files to regenerate; tests and `make fuzz` write them into
a fresh folder each time. Standard library only (runs under the system python3 from make).

    python3 fuzz/gen_seeds.py OUT_DIR     -> OUT_DIR/{serial,can,nvm,bridge}/seed-NNN

Input formats: the comment at the top of each fuzz_<target>.c (and fuzz_common.h for the streams).
"""

from __future__ import annotations

import struct
import sys
import zlib
from pathlib import Path

# cfg bits shared by the serial target: bit 0 identity, bits 1-2 NVM preset, bit 3 fix checksums
SERIAL_FIX = 0x08
NVM_MAGIC = 0x4C414346


def frame(body: str) -> bytes:
    """`$BODY*HH\\n` with the XOR checksum (design 3.1)."""
    x = 0
    for ch in body.encode():
        x ^= ch
    return f"${body}*{x:02X}\n".encode()


def crc_f32(values: list[float]) -> int:
    """CRC-32 (zlib) of float32 little-endian values (design 3.1's coefficient CRC)."""
    return zlib.crc32(struct.pack(f"<{len(values)}f", *values))


def sample_record(reps: int, temp_step: int, acc: tuple[int, int, int], temp: int) -> bytes:
    """0x00 marker + reps, temperature step, 3 x int32 acceleration, int32 temperature."""
    return b"\x00" + struct.pack("<Bb4i", reps, temp_step, *acc, temp)


THERMAL = [0.25, -0.5, 1.0, -120.0, 40.0, -250.0]
SFEM = [1.001, 0.002, -0.001, 0.0005, 0.998, 0.003, -0.002, 0.001, 1.0004, 0.012, -0.008, 0.02]
CUBIC = [[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.01, -0.02, 0.005],
         [1e-5, 0.0, 0.0, 0.0, -2e-5, 0.0, 0.0, 0.0, 3e-6, 2e-4, -1e-4, 5e-5],
         [1e-7, 0.0, 0.0, 0.0, 1e-7, 0.0, 0.0, 0.0, -1e-7, 1e-6, 0.0, 0.0],
         [1e-9, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1e-9, 0.0, 1e-8, 0.0]]


def cubic_commands(t_ref: float = 25.0, t_lo: float = -10.0, t_hi: float = 60.0) -> list[str]:
    """$SFTW x 4 then $SFTC with the CRC of the 51 values (contract: version-2 record)."""
    cmds = [f"SFTW,{k}," + ",".join(repr(v) for v in CUBIC[k]) for k in range(4)]
    crc = crc_f32([t_ref, t_lo, t_hi] + [v for row in CUBIC for v in row])
    cmds.append(f"SFTC,{t_ref!r},{t_lo!r},{t_hi!r},{crc:08X}")
    return cmds


def serial_commands() -> list[str]:
    """One of every 3.1 command the board knows (and the issue-42 additions), well formed."""
    return ["ID", "START", "STOP", "ODR,50", "ODR,3.125", "ODR,12.5", "ODR,7",
            "CALW," + ",".join(repr(v) for v in THERMAL), "CALR",
            "SFEW," + ",".join(repr(v) for v in SFEM), "SFER", "COMP,1", "COMP,0",
            *cubic_commands(), "SFTR,H", "SFTR,0", "SFTR,3", "SCAL,1", "SCRR", "SCAL,0"]


def serial_seeds() -> list[bytes]:
    cmds = serial_commands()
    seeds = [bytes([cfg]) + frame(c) for cfg in (SERIAL_FIX, SERIAL_FIX | 1, SERIAL_FIX | 4) for c in cmds]
    # a whole session: calibrate, compensate, stream samples at two temperatures
    session = b"".join(frame(c) for c in ["CALW," + ",".join(repr(v) for v in THERMAL),
                                           "SFEW," + ",".join(repr(v) for v in SFEM), "COMP,1", "START"])
    session += sample_record(4, 1, (9600, -9600, 9600), 20) + sample_record(4, -1, (-9600, 9600, -9600), 60)
    seeds.append(bytes([SERIAL_FIX]) + session)
    seeds.append(bytes([SERIAL_FIX | 1]) + b"".join(frame(c) for c in cubic_commands()) + frame("COMP,1")
                 + sample_record(2, 3, (150000, -150000, 150000), 1885))
    # on-board self-calibration: orientation P, hot, then N, hot (1500+ samples per segment)
    scal = frame("SCAL,1")
    for acc, temp, step in (((9600, 9600, 9600), 20, 0), ((9600, 9600, 9600), 45, 0),
                            ((-9600, -9600, -9600), 45, 0), ((-9600, -9600, -9600), 20, 0)):
        scal += sample_record(255, step, acc, temp)
    seeds.append(bytes([SERIAL_FIX]) + scal + frame("SCRR"))
    # garbage around frames, CRLF, a bad checksum, an overlong line, a re-init report
    seeds.append(bytes([0]) + b"xx" + frame("ID") + b"$ID*00\n" + frame("START")[:-1] + b"\r\n" + b"A" * 250 + b"\n"
                 + b"\x01\x10\x27" + frame("ID"))
    # non-finite values: every command that takes numbers must refuse them (E,<cmd>,non-finite value)
    for body in ("CALW,nan,0,0,0,0,0", "CALW,0,0,0,0,0,inf", "SFEW,1,0,0,0,1,0,0,0,1,0,0,-inf",
                 "SFTW,0,nan,0,0,0,1,0,0,0,1,0,0,0", "SFTC,nan,-10,60,00000000", "ODR,nan", "CALW,1e39,0,0,0,0,0"):
        seeds.append(bytes([SERIAL_FIX]) + frame(body) + frame("CALR"))
    # the self-calibrator fed the extremes of the int32 counts the bridge can carry
    seeds.append(bytes([SERIAL_FIX]) + frame("SCAL,1") + sample_record(0, 0, (0, 0, 0), -2**31)
                 + sample_record(0, 0, (2**31 - 1, -2**31, 0), 2**31 - 1))
    seeds.append(bytes([0x80 | SERIAL_FIX, 1, 2, 3, 4, 0, 0, 0, 0]) + frame("CALW," + ",".join(repr(v) for v in THERMAL))
                 + frame("COMP,1") + frame("CALR"))
    return seeds


def can_record(data: bytes, tag: int = 0, can_id: int = 0) -> bytes:
    """12-byte record: tag, id (used when tag bit 1), dlc, 8 data bytes."""
    return struct.pack("<BHB", tag, can_id, len(data)) + data.ljust(8, b"\x00")


def can_sample(reps: int, temp_step: int, acc: tuple[int, int, int], temp: int) -> bytes:
    """12-byte sample record: tag 1, unused, temperature step, reps, 3 x int16 acceleration, int16 temperature."""
    return struct.pack("<BBbB4h", 1, 0, temp_step, reps, *acc, temp)


def can_seeds() -> list[bytes]:
    node = 5
    cmds = [b"\x01", b"\x02", b"\x03", b"\x04" + struct.pack("<f", 50.0), b"\x04" + struct.pack("<f", 7.0), b"\x07",
            b"\x08\x01", b"\x08\x00"]
    cal = [b"\x05" + bytes([k]) + struct.pack("<f", v) for k, v in enumerate(THERMAL)]
    f32 = list(struct.unpack("<6f", struct.pack("<6f", *THERMAL)))
    commit = b"\x06" + struct.pack("<I", crc_f32(f32))
    seeds = [bytes([cfg, node - 1]) + can_record(c) for cfg in (0, 1, 4) for c in cmds]
    seeds.append(bytes([0, node - 1]) + b"".join(can_record(c) for c in cal) + can_record(commit) + can_record(b"\x07")
                 + can_record(b"\x08\x01") + can_sample(4, 1, (9600, -9600, 9600), 20))
    seeds.append(bytes([1, node - 1]) + can_record(b"\x03", tag=2, can_id=0x600 + node)
                 + can_record(b"\x01", tag=2, can_id=0x123) + can_sample(1, -2, (-20000, 20000, 100), 1885))
    seeds.append(bytes([0x80, node - 1]) + b"".join(can_record(c) for c in cal) + can_record(commit))
    # contract 3.2: a non-finite CAL_FIELD is refused at CAL_COMMIT (status 1), even with its right CRC
    bad = [b"\x05\x00" + struct.pack("<I", 0x7FC00000)] + cal[1:]
    bad_f32 = [float("nan")] + f32[1:]
    bad_crc = zlib.crc32(struct.pack("<I", 0x7FC00000) + struct.pack("<5f", *bad_f32[1:]))
    seeds.append(bytes([0, node - 1]) + b"".join(can_record(c) for c in bad) + can_record(b"\x06" + struct.pack("<I", bad_crc))
                 + can_record(b"\x07"))
    seeds.append(bytes([0, node - 1]) + b"".join(can_record(c) for c in cal) + can_record(b"\x06\x00\x00\x00\x00", tag=4))
    return seeds


SLOT_BYTES = 512  # core/fw_hal.h FW_NVM_SLOT_BYTES (256 before issue 42: a version-2 record is 312 bytes)
ERASED = b"\xff" * SLOT_BYTES


def _record_head(version: int, length: int, generation: int, thermal: list[float], sfem: list[float] | None,
                 comp: bool) -> bytearray:
    """Bytes 0..99 shared by both layouts (core/fw_nvm.h), in a buffer of the record's length."""
    th = struct.pack("<6f", *thermal)
    rec = bytearray(length)
    struct.pack_into("<IHHI", rec, 0, NVM_MAGIC, version, length, generation)
    rec[12:36] = th
    struct.pack_into("<I", rec, 36, zlib.crc32(th))
    if sfem is not None:
        sf = struct.pack("<12f", *sfem)
        rec[40] = 1
        rec[44:92] = sf
        struct.pack_into("<I", rec, 92, zlib.crc32(sf))
    rec[96] = 1 if comp else 0
    return rec


def nvm_record_v1(thermal: list[float], sfem: list[float] | None, comp: bool, generation: int) -> bytes:
    """A version-1 record (104 bytes), padded erased to the slot."""
    rec = _record_head(1, 104, generation, thermal, sfem, comp)
    struct.pack_into("<I", rec, 100, zlib.crc32(bytes(rec[:100])))
    return bytes(rec) + b"\xff" * (SLOT_BYTES - 104)


def nvm_record_v2(thermal: list[float], sfem: list[float] | None, comp: bool, generation: int,
                  head: tuple[float, float, float] = (25.0, -10.0, 60.0)) -> bytes:
    """A version-2 record (312 bytes: version 1 plus t_ref/t_lo/t_hi, the cubic c[4][12], their CRC)."""
    rec = _record_head(2, 312, generation, thermal, sfem, comp)
    cubic = struct.pack("<3f", *head) + b"".join(struct.pack("<12f", *row) for row in CUBIC)
    rec[100:304] = cubic
    struct.pack_into("<I", rec, 304, zlib.crc32(cubic))
    struct.pack_into("<I", rec, 308, zlib.crc32(bytes(rec[:308])))
    return bytes(rec) + b"\xff" * (SLOT_BYTES - 312)


def nvm_seeds() -> list[bytes]:
    a = nvm_record_v1(THERMAL, None, True, 1)
    b = nvm_record_v1(THERMAL, SFEM, True, 2)
    c = nvm_record_v1([0.0] * 6, None, False, 0xFFFFFFFF)
    v2 = nvm_record_v2(THERMAL, SFEM, True, 3)
    torn = b[:60] + b"\xff" * (SLOT_BYTES - 60)
    torn2 = v2[:200] + b"\xff" * (SLOT_BYTES - 200)
    stream = frame("CALW," + ",".join(repr(v) for v in THERMAL)) + frame("COMP,0") + sample_record(1, 0, (100, 200, 300), 30)
    seeds = []
    for cfg in (0x00, 0x08, 0x04):
        for s0, s1 in ((ERASED, ERASED), (a, ERASED), (a, b), (b, torn), (torn, ERASED), (c, a), (v2, ERASED),
                       (b, v2), (v2, torn2)):
            seeds.append(bytes([cfg]) + s0 + s1 + (stream if not cfg & 4 else can_record(b"\x07")))
    seeds.append(bytes([0x13]) + a + b + stream)           # CRCs recomputed by the harness, flash faults
    # records whose CRCs all check but whose coefficients are not finite: the board must not apply them
    nan_th = bytearray(a)
    nan_th[12:16] = struct.pack("<I", 0x7FC00000)
    inf_sf = bytearray(b)
    inf_sf[44:48] = struct.pack("<I", 0xFF800000)
    seeds.append(bytes([0x03]) + bytes(nan_th) + bytes(inf_sf) + stream)
    seeds.append(bytes([0x01]) + bytes(inf_sf) + ERASED + stream)
    nan_cubic = bytearray(v2)
    nan_cubic[112 + 48 * 2:116 + 48 * 2] = struct.pack("<I", 0x7FC00000)   # c[2][0]
    seeds.append(bytes([0x01]) + bytes(nan_cubic) + a + stream)
    seeds.append(bytes([0x02]) + a + nvm_record_v2(THERMAL, None, True, 9, head=(25.0, 60.0, -10.0)) + stream)  # t_lo > t_hi
    seeds.append(bytes([0xF0]) + a + ERASED + stream)      # every write faulty
    return seeds


def bridge_seeds() -> list[bytes]:
    ident = [frame("B,SIM0001,LIS3DSH,60,1,0,3.125"), frame("B,F4000102030405060708090A0B,ADXL355,3.9,-9.05,1885,3.125")]
    samples = b"".join(frame(f"S,{320000 * k},{9600 + k},{-9600 - k},{16000},{20 + k // 4}") for k in range(12))
    seeds = []
    for cfg in (0x01, 0x02, 0x0B, 0x14):
        for idl in ident:
            seeds.append(bytes([cfg]) + idl + samples)
    seeds.append(bytes([0x05]) + ident[0] + samples + frame("X,selfcal_skew,0.5") + frame("X,hang") + ident[1] + samples)
    # text a station cannot frame ('$' starts a frame, '*' its checksum) must not reach a reply
    seeds.append(bytes([0x01]) + frame("B,SIM$1,LIS*3DSH,60,1,0,3.125") + samples)
    seeds.append(bytes([0x01]) + b"junk\n" + frame("S,1,2,3,4,5") + ident[0] + frame("S,4294967296,1,2,3,4")
                 + frame("S,-1,0,0,0,0") + b"$S,1,2*00\r\n")
    return seeds


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print(__doc__)
        return 2
    out = Path(argv[1])
    counts = {}
    for name, seeds in (("serial", serial_seeds()), ("can", can_seeds()), ("nvm", nvm_seeds()), ("bridge", bridge_seeds())):
        d = out / name
        d.mkdir(parents=True, exist_ok=True)
        for k, seed in enumerate(seeds):
            (d / f"seed-{k:03d}").write_bytes(seed)
        counts[name] = len(seeds)
    print("seeds:", ", ".join(f"{k} {v}" for k, v in counts.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
