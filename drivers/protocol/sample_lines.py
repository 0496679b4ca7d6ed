"""Sample frames in bulk: a read of N clean `$D,...*HH` lines decoded with numpy, not line by line.

Why: at 64 boards the per-line parser (serial_frames.FrameParser) was the station's largest cost
per sample (issue 40: a checksum, a split and six int() per line, in Python). A board's stream is,
almost always, nothing but sample lines; this module decodes such a run at once and says None
for anything else, so the per-line parser stays the one definition of the format and handles every
line this one is not sure of: a reply, garbage, a bad checksum, a field out of range, a sign or a
digit where the contract does not put one. `decode_sample_lines` accepts a run only when every line
is a sample frame the per-line parser would also accept with the same numbers
(tests/test_sample_lines.py holds it to that on random and hostile input).

Pure: bytes in, arrays out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_DIGITS_MAX = 18  # int64 holds every 18-digit number: longer fields go to the per-line parser
_HEX = np.full(256, -1, dtype=np.int16)
for _i, _c in enumerate(b"0123456789"):
    _HEX[_c] = _i
for _i, _c in enumerate(b"abcdef"):
    _HEX[_c] = 10 + _i
    _HEX[_c - 32] = 10 + _i
_POW10 = 10 ** np.arange(_DIGITS_MAX, dtype=np.int64)
_ALLOWED = np.zeros(256, dtype=bool)  # what a sample frame's fields may hold
_ALLOWED[list(b"0123456789,-")] = True
_U32_MAX = (1 << 32) - 1
_I32_MIN, _I32_MAX = -(1 << 31), (1 << 31) - 1


@dataclass(frozen=True)
class SampleLines:
    """Decoded sample frames, in order: seq (uint32), board clock (us) and raw counts (ax, ay, az, t)."""

    seq: np.ndarray  # int64
    t_us: np.ndarray  # int64
    counts: np.ndarray  # int64, (n, 4)

    def __len__(self) -> int:
        return len(self.seq)


def decode_sample_lines(region: bytes) -> SampleLines | None:
    """`region`: whole lines, each ending in b"\\n". The sample frames they hold when every line is
    a clean sample frame (`$D,seq,t_us,ax,ay,az,t*HH`, digits and a leading '-' only, checksum
    right, values in range); None otherwise (the per-line parser then reads them)."""
    if not region.startswith(b"$D,"):
        return None
    buf = np.frombuffer(region, dtype=np.uint8)
    nl = np.flatnonzero(buf == 10)
    n = len(nl)
    if n == 0 or nl[-1] != len(buf) - 1:
        return None
    starts = np.empty(n, dtype=np.int64)
    starts[0] = 0
    starts[1:] = nl[:-1] + 1
    # each line: '$' 'D' ',' ... '*' H H '\n', and '$' / '*' nowhere else
    if (nl - starts < 8).any():
        return None
    if (region.count(b"$") != n or region.count(b"*") != n or region.count(b"$D,") != n):
        return None
    if not ((buf[starts] == 36).all() and (buf[starts + 1] == 68).all() and (buf[starts + 2] == 44).all()
            and (buf[nl - 3] == 42).all()):
        return None
    hi, lo = _HEX[buf[nl - 2]], _HEX[buf[nl - 1]]
    if (hi < 0).any() or (lo < 0).any():
        return None
    # the body (between '$' and '*'): its XOR from a running XOR of the whole region
    cx = np.bitwise_xor.accumulate(buf)
    body_end = nl - 4  # last byte of the body
    xor = cx[body_end] ^ cx[starts]  # bytes starts+1 .. body_end
    if (xor != (hi * 16 + lo)).any():
        return None
    # fields: after "$D," up to '*': digits, ',' and '-' only; 6 fields per line, none empty, a '-'
    # only first in its field and followed by a digit
    fields_mask = np.ones(len(buf), dtype=bool)
    fields_mask[starts] = fields_mask[starts + 1] = fields_mask[starts + 2] = False
    for k in range(4):
        fields_mask[nl - k] = False
    if not _ALLOWED[buf[fields_mask]].all():
        return None
    # each field ends at a separator: a comma inside the fields, or the '*'
    is_comma = (buf == 44) & fields_mask
    commas = np.flatnonzero(is_comma)
    if len(commas) != 5 * n or (np.bincount(np.searchsorted(nl, commas), minlength=n) != 5).any():
        return None
    ends = np.sort(np.concatenate([commas, nl - 3]))
    if (_HEX[buf[ends - 1]] > 9).any() or (_HEX[buf[ends - 1]] < 0).any():  # the byte before each end: a digit
        return None
    minus = np.flatnonzero((buf == 45) & fields_mask)
    if len(minus) and ((buf[minus - 1] != 44).any() or (_HEX[buf[minus + 1]] < 0).any()
                       or (_HEX[buf[minus + 1]] > 9).any()):
        return None
    digits = np.flatnonzero(fields_mask & ~is_comma & (buf != 45))
    field = np.searchsorted(ends, digits)  # the field each digit belongs to
    exponent = ends[field] - digits - 1
    if len(digits) == 0 or int(exponent.max()) >= _DIGITS_MAX:
        return None
    terms = (buf[digits].astype(np.int64) - 48) * _POW10[exponent]
    first = np.flatnonzero(np.diff(field, prepend=-1))  # every field has a digit (checked above)
    vals = np.add.reduceat(terms, first)
    if len(minus):
        vals[np.searchsorted(ends, minus)] *= -1
    vals = vals.reshape(n, 6)
    seq, t_us, counts = vals[:, 0], vals[:, 1], vals[:, 2:]
    if (seq < 0).any() or (seq > _U32_MAX).any() or (t_us < 0).any():
        return None
    if (counts < _I32_MIN).any() or (counts > _I32_MAX).any():
        return None
    return SampleLines(seq=seq, t_us=t_us, counts=counts)
