"""The judged measurements in words, with units as an engineer writes them: "TDB x (mg/°C)".

A parameter is `measurement` or `measurement:axis` (station/records/spc.py). The words and units are
the measurements' declarations (station/decisions/measurements.py: `title`, `shown_unit`), so every
measurement the verdict can judge has them, a check's own measurement included (tests/test_spc.py),
and the Records view never shows a raw `tdb_mg_per_c:x`. An unknown name (a site's own
measurement) is still shown in words: underscores as spaces, with the unit its checks carry.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping

from station.decisions.measurements import declaration, declared, readable_unit


class _Words(Mapping[str, tuple[str, str]]):
    """measurement -> (words, unit as shown), read from the declarations when asked."""

    def __getitem__(self, name: str) -> tuple[str, str]:
        d = declaration(name)
        if d is None:
            raise KeyError(name)
        return d.title, d.shown_unit

    def __iter__(self) -> Iterator[str]:
        return iter([d.name for d in declared()])

    def __len__(self) -> int:
        return len(declared())


# measurement -> (words, unit as shown). The unit strings of the checks ("mg/C", "ug/sqrt(Hz)") are
# ASCII for logs and CSV; a person reads °C, µg and √Hz.
WORDS: Mapping[str, tuple[str, str]] = _Words()


def split(parameter: str) -> tuple[str, str | None]:
    """('tdb_mg_per_c', 'x') from 'tdb_mg_per_c:x'; axis None for a per-DUT measurement."""
    m, _, ax = parameter.partition(":")
    return m, (ax or None)


def unit_words(measurement: str, check_unit: str = "") -> str:
    """The unit as shown: the declaration's, else the check's own unit made readable."""
    d = declaration(measurement)
    return d.shown_unit if d is not None else readable_unit(check_unit)


def words(parameter: str) -> str:
    """'TDB x' (no unit): for the failure Pareto, where the count is the number."""
    m, ax = split(parameter)
    d = declaration(m)
    w = d.title if d is not None else m.replace("_", " ").strip() or "unnamed"
    return f"{w} {ax}" if ax else w


def label(parameter: str, check_unit: str = "") -> str:
    """'TDB x (mg/°C)', 'TDSF z (ppm/°C)', 'lost samples (%)'."""
    m, _ax = split(parameter)
    u = unit_words(m, check_unit)
    return f"{words(parameter)} ({u})" if u else words(parameter)


__all__ = ["WORDS", "split", "unit_words", "words", "label"]
