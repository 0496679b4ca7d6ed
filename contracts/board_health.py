"""What a board says of its own health in its identity (docs/design.md 3.1/3.2).

A board with the issue-42 firmware adds optional `key=value` fields to its `I` reply (and a CAN
frame 11): why it last started (`reset`), how often it started since power-up (`boots`), what a
fault left behind (`fault`, `fault_pc`), which NVM record is in force (`rec_*`), what it can do
beyond the base protocol (`caps`) and how often it re-initialised a silent sensor
(`sensor_reinit`). None of it says WHICH board this is (contracts/types.Identity compares without
it): it says what the board went through, so a restart during a run (its `boots` moved) can end
that run with the cause in words instead of passing a run that was two boards' lives.

Pure records and words; the wire codecs are drivers/protocol/serial_frames.py and can_frames.py.
"""

from __future__ import annotations

from dataclasses import dataclass

# why a board last started (contract 3.1 `reset=`; CAN frame 11 byte 1 is the index in this tuple)
RESET_CAUSES: tuple[str, ...] = ("unknown", "power", "pin", "watchdog", "fault", "brownout", "software")
# the state of the NVM record in force (contract 3.1 `rec_state=`; CAN frame 11 byte 2 is the index)
RECORD_STATES: tuple[str, ...] = ("ok", "fallback", "empty", "corrupt")

CAP_SELFCAL = "scal"  # the on-board streaming calibrator ($SCAL / $SCRR, design 3.1)
CAP_SFEM_CUBIC = "sfem3"  # the version-2 record: the cubic thermal SFEM ($SFTW / $SFTC / $SFTR)


@dataclass(frozen=True)
class BoardRecordInfo:
    """The NVM record a board has in force, as it reports it (`rec_ver`, `rec_gen`, `rec_slot`,
    `rec_state`); a field the board did not send is None. rec_ver 0 / rec_slot None: no record.
    `fallback` means a newer slot is damaged and an older record is applied: the board runs with
    coefficients that are not the last ones written, which a station wants to see in words."""

    rec_ver: int | None = None
    rec_gen: int | None = None
    rec_slot: int | None = None
    rec_state: str | None = None

    def words(self) -> str:
        """e.g. "record v2 gen 7 slot 1 ok" (fields not reported are left out)."""
        parts = ["record"]
        if self.rec_ver is not None:
            parts.append(f"v{self.rec_ver}")
        if self.rec_gen is not None:
            parts.append(f"gen {self.rec_gen}")
        if self.rec_slot is not None:
            parts.append(f"slot {self.rec_slot}")
        if self.rec_state is not None:
            parts.append(self.rec_state)
        return " ".join(parts)


def reset_words(reset_cause: str | None, fault_cfsr: int | None = None, fault_pc: int | None = None) -> str:
    """A reset cause as an operator reads it: "watchdog reset", "fault reset at pc 0x08001A2C
    (CFSR 0x00000400)", "reset (cause not reported)". The fault's PC is what a firmware engineer
    needs first (which code faulted), so it is always shown in hex when the board gave it."""
    if reset_cause is None:
        return "reset (cause not reported)"
    words = f"{reset_cause} reset"
    if fault_pc is not None:
        words += f" at pc 0x{fault_pc:08X}"
    if fault_cfsr is not None:
        words += f" (CFSR 0x{fault_cfsr:08X})"
    return words
