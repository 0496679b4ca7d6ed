"""The ctypes mirrors of the firmware core's structs (firmware/core/fw_board.h, fw_hal.h), shared by
tests/test_firmware_core.py and tests/test_firmware_records.py.

One copy: the arrays are sized from the C headers' own #defines, and test_firmware_core checks each
mirror against fw_layout() (the C's sizes and offsets), so a layout change fails there by name
instead of corrupting memory in either file.
"""

from __future__ import annotations

import ctypes as C
import re
from pathlib import Path

CORE = Path(__file__).resolve().parents[1] / "firmware" / "core"


def header_define(header: str, name: str) -> int:
    """A `#define NAME 123u` of a core header: the mirrors size their arrays from the C."""
    m = re.search(rf"#define\s+{name}\s+(\d+)u", (CORE / header).read_text())
    assert m, name
    return int(m.group(1))


SERIAL_MAX = header_define("fw_board.h", "FW_SERIAL_MAX")


class FwIdentity(C.Structure):
    _fields_ = [("serial", C.c_char * (SERIAL_MAX + 1)), ("sensor", C.c_char * 16), ("fw", C.c_char * 16),
                ("ug_per_lsb", C.c_float), ("t_lsb_per_c", C.c_float), ("t_lsb_at_25c", C.c_float),
                ("odr_hz", C.c_float)]


UART_FN = C.CFUNCTYPE(None, C.c_void_p, C.POINTER(C.c_uint8), C.c_uint32)
CAN_FN = C.CFUNCTYPE(None, C.c_void_p, C.c_uint16, C.c_uint8, C.POINTER(C.c_uint8))
NVM_RD = C.CFUNCTYPE(C.c_int, C.c_void_p, C.c_uint32, C.POINTER(C.c_uint8), C.c_uint32)
NVM_WR = C.CFUNCTYPE(C.c_int, C.c_void_p, C.c_uint32, C.POINTER(C.c_uint8), C.c_uint32)


class FwHal(C.Structure):
    _fields_ = [("ctx", C.c_void_p), ("uart_write", UART_FN), ("can_send", CAN_FN),
                ("nvm_read", NVM_RD), ("nvm_write", NVM_WR)]


class FwRawSample(C.Structure):
    _fields_ = [("t_us", C.c_uint32), ("acc", C.c_int32 * 3), ("temp", C.c_int32)]
