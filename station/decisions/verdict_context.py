"""What the verdict's moment (moment.py) reads of the station and of a batch, as typed values.

Why typed: the moment once read the station by attribute name (`getattr(station, "_profiles", {})`), an
attribute the Station never had. The silent default judged every run a killed daemon left behind as
a thermal profile's, so after each restart a validation run (a profile with no analysis, never to be
judged) went to the MES as `error` and first-pass yield dropped. Nothing failed; no test noticed.

So the moment takes no station at all. `VerdictContext` names each part it reads, with its type, and
the Station fills it once where it is built (station/daemon/supervisor.py): a renamed attribute is an
AttributeError when any Station is constructed (every daemon test builds one) and an error for a type
checker, never a default at a restart. `__post_init__` checks the parts by their shape as well, so a
wrong object (a config where the profiles belong, a database without `resume_point`) fails there too,
not at the first crash in production. `EndedBatch` is what the moment reads of a released batch (the
Sequencer is one): a Protocol, so a test may hand it a plain namespace with the same names.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, runtime_checkable

from contracts.events import Event
from contracts.trace import Trace
from station.decisions.limits import ProductSpec
from station.profiles import Profile

if TYPE_CHECKING:  # types only: the moment reads these records, it never builds them
    from db.database import ResumePoint
    from station.daemon.dut_run import DutRun


@runtime_checkable
class VerdictStore(Protocol):
    """The database calls the moment makes (db.database.Database has them)."""

    def run_attempt(self, run_id: int) -> int:
        """The run's attempt number; KeyError for a run the database does not know."""
        ...

    def resume_point(self, batch_id: int) -> "ResumePoint":
        """A batch's profile and runs (the runs a killed daemon left); KeyError for an unknown batch."""
        ...

    def batch_trace(self, batch_id: int) -> Trace:
        """What the batch was started for (its part number chooses the product's limits)."""
        ...

    def unjudged_runs(self, exclude_batches: list[int]) -> dict[int, list[int]]:
        """Runs of this station that ended with no verdict stored: {batch id: [run ids]}."""
        ...


@runtime_checkable
class Publisher(Protocol):
    """Where a verdict goes: the event bus (its DutVerdict is the one record the MES gets)."""

    def publish(self, event: Event) -> None: ...


# (sensor, part number) -> the product whose limits judge the DUT (StationConfig.product_for)
ProductLookup = Callable[[str | None, str | None], ProductSpec | None]
# slot -> its live link's counters now (None: no driver; the run's stored counters are used)
LinkStatsLookup = Callable[[str], "Mapping[str, int] | None"]


def no_live_links(slot: str) -> Mapping[str, int] | None:
    """A station without live links (a test, a records-only tool): the runs' own counters count."""
    return None


@dataclass(frozen=True)
class VerdictContext:
    """Everything of the station the verdict's moment reads, each part typed (see the module doc)."""

    db: VerdictStore
    bus: Publisher
    product_for: ProductLookup
    profiles: Mapping[str, Profile]  # every profile by name (built-ins and the site's)
    live_link_stats: LinkStatsLookup = no_live_links

    def __post_init__(self) -> None:
        missing = [name for name in ("run_attempt", "resume_point", "batch_trace", "unjudged_runs")
                   if not callable(getattr(self.db, name, None))]
        if missing:
            raise TypeError(f"VerdictContext.db: {type(self.db).__name__} has no {', '.join(missing)}")
        if not isinstance(self.bus, Publisher):
            raise TypeError(f"VerdictContext.bus: {type(self.bus).__name__} has no publish()")
        for name in ("product_for", "live_link_stats"):
            if not callable(getattr(self, name)):
                raise TypeError(f"VerdictContext.{name} is not callable")
        if not isinstance(self.profiles, Mapping):
            raise TypeError(f"VerdictContext.profiles: a mapping of name to Profile, not {type(self.profiles).__name__}")
        wrong = [name for name, p in self.profiles.items() if not isinstance(p, Profile)]
        if wrong:
            raise TypeError(f"VerdictContext.profiles: not a Profile: {', '.join(map(str, wrong))}")


@runtime_checkable
class BoardOpinions(Protocol):
    """The boards' own calibrators of a batch (station/daemon/board_selfcal.py BoardCalibrators):
    the opinion the verdict judges per slot, as its JSON (contracts/selfcal_opinion.py)."""

    def opinion_of(self, slot: str) -> Mapping[str, object]: ...


class EndedBatch(Protocol):
    """What the moment reads of a batch whose DUTs were released (station/daemon/sequencer.py)."""

    @property
    def batch_id(self) -> int: ...

    @property
    def profile(self) -> Profile: ...

    @property
    def duts(self) -> "Sequence[DutRun]": ...

    @property
    def ending(self) -> str | None: ...

    @property
    def state(self) -> str: ...

    @property
    def error(self) -> str: ...

    @property
    def trace(self) -> Trace: ...


__all__ = ["VerdictContext", "VerdictStore", "Publisher", "EndedBatch", "BoardOpinions", "ProductLookup", "LinkStatsLookup",
           "no_live_links"]
