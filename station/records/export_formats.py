"""The export formats (docs/exports.md): one registered writer each.

An `ExportFormat` is everything the command line (`station export NAME`: choices, help, the title it
prints), the REST API (`GET /api/batches/{id}/export.SUFFIX` and `/api/runs/{id}/export.SUFFIX`:
media type, file name, OpenAPI text) and the web's repository (which writer) need to know about a
format. The built-in formats are listed once below; a new one is one `register(ExportFormat(...))`
with a pure writer (ExportReport -> bytes), and every reader picks it up: the command line when it
builds its parser, the web app when it is created (web/routes/exports.py).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

from contracts.types import NotFound

if TYPE_CHECKING:
    from station.records.export_model import ExportReport


@dataclass(frozen=True)
class ExportFormat:
    name: str  # the CLI's word and the key: `station export NAME`
    title: str  # what the CLI says it wrote: "<file>: TITLE of batch 3: ..."
    media_type: str  # REST Content-Type
    suffix: str  # REST path `export.SUFFIX` and the downloaded file's extension
    write: Callable[[ExportReport], bytes]  # pure: report -> bytes
    help: str = ""  # CLI help of the format word ("STDF V4 (binary)")
    description: str = ""  # OpenAPI description of the 200 answer ("STDF V4, little-endian")
    batch_doc: str = ""  # OpenAPI text of the batch route (default: "Every DUT run of the batch as TITLE.")
    run_doc: str = ""  # OpenAPI text of the run route (default: "One DUT run as TITLE.")

    def __post_init__(self) -> None:
        if not re.fullmatch(r"[a-z][a-z0-9_]*", self.name):
            raise ValueError(f"export format name {self.name!r}: lower-case letters, digits and _ only")
        if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", self.suffix):
            raise ValueError(f"export format suffix {self.suffix!r}: no '/', no leading dot")
        if not callable(self.write):
            raise ValueError(f"export format {self.name!r}: write must be callable (ExportReport -> bytes)")


# The built-in writers are imported when a file is written, not when a parser or app lists the
# formats (the report model pulls in the database package: every `station` command builds the parser).
def write_stdf(report: ExportReport) -> bytes:
    from station.records.export_stdf import write_stdf as write

    return write(report)


def write_ocptv(report: ExportReport) -> bytes:
    from station.records.export_ocptv import write_ocptv as write

    return write(report)


STDF = ExportFormat(
    name="stdf", title="STDF V4", media_type="application/octet-stream",  # STDF has no registered media type
    suffix="stdf", write=write_stdf, help="STDF V4 (binary)", description="STDF V4, little-endian",
    batch_doc="Every DUT run of the batch as STDF V4: MIR with lot, part number, revision and work order;\n"
              "per DUT PIR, a PTR per judged measurement (limits, units) and PRR (serial, pass flag, bins).",
    run_doc="One DUT run as STDF V4 (one part).")
OCPTV = ExportFormat(
    name="ocptv", title="OCPTV JSON",
    media_type="application/x-ndjson",  # line-delimited JSON, one artifact per line
    suffix="ocptv.json", write=write_ocptv, help="OCP Test & Validation JSON lines (one testRun per DUT run)",
    description="OCPTV 2.0 JSON lines, one testRun per DUT run",
    batch_doc="Every DUT run of the batch as OCP Test & Validation output: one testRun per run, each\n"
              "starting with its schemaVersion line; measurements with validators, one diagnosis per verdict.",
    run_doc="One DUT run as OCP Test & Validation output (one testRun).")

_FORMATS: dict[str, ExportFormat] = {f.name: f for f in (STDF, OCPTV)}


def register(fmt: ExportFormat) -> ExportFormat:
    """Add a format (before the parser or the web app is built). A name or suffix already taken by
    another format is refused; registering the same format again changes nothing."""
    for other in _FORMATS.values():
        if other == fmt:
            return fmt
        if other.name == fmt.name or other.suffix == fmt.suffix:
            raise ValueError(f"export format {fmt.name!r} (export.{fmt.suffix}) clashes with "
                             f"{other.name!r} (export.{other.suffix})")
    _FORMATS[fmt.name] = fmt
    return fmt


def unregister(name: str) -> None:
    """Remove a format (a test's own); an unknown name is no error."""
    _FORMATS.pop(name, None)


def export_formats() -> dict[str, ExportFormat]:
    """The registered formats by name, in registration order (a copy)."""
    return dict(_FORMATS)


def export_format(name: str) -> ExportFormat:
    """The format called `name`; KeyError naming the known ones otherwise."""
    try:
        return _FORMATS[name]
    except KeyError:
        raise NotFound(f"unknown export format {name!r} (known: {', '.join(_FORMATS)})") from None


__all__ = ["OCPTV", "STDF", "ExportFormat", "export_format", "export_formats", "register", "unregister"]
