"""slcan (Lawicel) receive lines, parsed in bulk (pure: bytes in, frames out).

python-can's slcan reader takes the adapter's bytes one `Serial.read(1)` call at a time, which was
~40 % of the daemon's CPU with 16 CAN boards. The CAN bus reader (drivers/can_board.py)
reads whatever the port holds in one call and splits it here. Only what the station uses is
decoded: standard data frames `tIIILDD..\\r`; extended/remote/FD frames and the adapter's acks
(`\\r`, `z\\r`, `Z\\r`) and errors (BEL) are skipped; a line that is not a well-formed frame is
counted as garbled (line noise), never raised.
"""

from __future__ import annotations

CR = 0x0D
BEL = 0x07
_HEX = frozenset(b"0123456789abcdefABCDEF")
MAX_LINE = 64  # longer than any classic frame line: garbage without a CR


def split_frames(buf: bytearray) -> tuple[list[tuple[int, bytes]], int]:
    """Consume the complete lines of `buf` (in place; a partial last line stays for the next read).

    Returns ([(arbitration_id, data), ...] of standard data frames, number of garbled lines)."""
    frames: list[tuple[int, bytes]] = []
    garbled = 0
    start = 0
    n = len(buf)
    while True:
        cr = buf.find(b"\r", start)
        bel = buf.find(b"\x07", start)
        end = cr if bel < 0 or (0 <= cr < bel) else bel
        if end < 0:
            break
        line = bytes(buf[start:end])
        start = end + 1
        if not line:
            continue  # an ack ("\r") or the adapter's error bell alone
        if buf[end] == BEL:
            garbled += 1  # a frame is never ended by the bell: whatever preceded it is noise
            continue
        kind = line[0]
        if kind == 0x74:  # 't': standard data frame
            frame = _standard(line)
            if frame is None:
                garbled += 1
            else:
                frames.append(frame)
        elif kind in (0x54, 0x72, 0x52, 0x64, 0x44, 0x62, 0x42, 0x7A, 0x5A, 0x46, 0x56, 0x76, 0x4E):
            continue  # T r R d D b B (not used here), z/Z acks, F status, V/v version, N serial
        else:
            garbled += 1
    rest = n - start
    if rest > MAX_LINE:  # no CR for longer than any frame: noise; keep the tail only
        garbled += 1
        start = n - MAX_LINE
    del buf[:start]
    return frames, garbled


def _standard(line: bytes) -> tuple[int, bytes] | None:
    if len(line) < 5 or not all(c in _HEX for c in line[1:5]):
        return None
    dlc = line[4] - 0x30
    if not 0 <= dlc <= 8 or len(line) not in (5 + 2 * dlc, 9 + 2 * dlc):  # + 4 hex digits: adapter timestamp
        return None
    payload = line[5:5 + 2 * dlc]
    if not all(c in _HEX for c in payload):
        return None
    return int(line[1:4], 16), bytes.fromhex(payload.decode("ascii"))
