"""The ranking of `station diagnose`, kept on disk between runs of the command, so that
`station diagnose LOG.csv --add EFFECT` after a first run refits only the models it adds instead of
ranking every candidate again (docs/diagnostics.md, "Speed").

Why a module of its own: what may be reused is a question of identity (the same log, the same
candidates, the same effect code, the same software), and a file on disk is data from outside: it is
looked at before it is believed. The ranking itself (ranking.Ranked) knows nothing of files.

What is kept: the `Ranked` state of ranking.diagnose (the prepared logs, the ranking, the admitted
staircase and every model fitted by the ranking), pickled, one file per question.

Where: the user's own cache directory, `$STATION_DIAGNOSE_CACHE` if set (a directory; `off`, `0`
or `no` switch the cache off), else `$XDG_CACHE_HOME/station/diagnose`, else
`~/.cache/station/diagnose`; created with mode 0700. Not beside the log: a log folder may be
shared, read-only or a repository's, `station diagnose` writes only where it is told (--plots,
--save-model), and a pickle is only as trustworthy as whoever could write it: a file in a folder
that is not the user's own, or that others may write, is never read. A folder that cannot be
created or written just means no cache (nothing is reported).

The key (file name and header, compared on every read): a format number, the software version
(station/version.py, given by the command line), a digest of the diagnostics' source
(station/diagnostics/*.py and contracts/*.py, so an edited source tree never reuses an old
ranking), the Python, numpy and scipy versions, each log's content (every column's values and
its `# key: value` header), the candidate effects in order with the code and source files that
define each (a user's --effects-file included: its content, not its name), the RMS basis and the
segmentation. A file is named by the key's hash, so another question never opens it; it is read
only when its header names that key, its length and SHA-256 match what the header says and it
unpickles into a ranking of as many logs, with their serials. Anything else (a truncated or
corrupted file, an unreadable one, an older format, one that is not the user's own) is ignored and
replaced by the next ranking. Files are replaced atomically (a temporary file renamed); the least
recently used are deleted beyond MAX_ENTRIES files or MAX_TOTAL_BYTES. Nothing about the cache
ever fails a diagnosis: any problem with it is a miss (logged at debug level).

The cache is off unless a caller switches it on for a while (`with enabled(...)`): the command line
does, a library call of ranking.diagnose (the web page, the tests) does not, so nothing is written
behind their back.
"""

from __future__ import annotations

import contextlib
import contextvars
import hashlib
import json
import logging
import os
import pickle
import platform
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

log = logging.getLogger(__name__)

FORMAT = 1  # of the file (header and payload); a change of the key's recipe changes it too
MAGIC = b"station-diagnose-cache\n"
SUFFIX = ".diag"
MAX_ENTRIES = 32  # files kept (a 10 h log's ranking: ~25 MB)
MAX_TOTAL_BYTES = 1 << 30
MAX_HEADER_BYTES = 1 << 16
ENV = "STATION_DIAGNOSE_CACHE"
OFF = ("off", "0", "no", "false", "none")
_HERE = Path(__file__).resolve().parent
SOURCE_DIRS = (_HERE, _HERE.parent.parent / "contracts")  # whose *.py the key's code digest covers


@dataclass(frozen=True)
class _Settings:
    directory: Path
    version: str


_SETTINGS: contextvars.ContextVar[_Settings | None] = contextvars.ContextVar("diagnose_disk_cache", default=None)


def default_directory() -> Path | None:
    """Where the cache lives (None: switched off by $STATION_DIAGNOSE_CACHE)."""
    env = os.environ.get(ENV, "").strip()
    if env:
        return None if env.lower() in OFF else Path(env).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME", "").strip()
    base = Path(xdg) if xdg else Path.home() / ".cache"
    return base / "station" / "diagnose"


@contextlib.contextmanager
def enabled(version: str, directory: str | Path | None = None) -> Iterator[Path | None]:
    """Within the block, ranking.diagnose reads and writes the cache in `directory` (default:
    default_directory()); `version` is the software's (station/version.py). Yields the directory
    (None when the cache is switched off)."""
    where = Path(directory).expanduser() if directory is not None else default_directory()
    token = _SETTINGS.set(_Settings(where, str(version)) if where is not None else None)
    try:
        yield where
    finally:
        _SETTINGS.reset(token)
        _forget()


# ---- the key --------------------------------------------------------------------------------------
_code_digest: str | None = None


def code_digest() -> str | None:
    """SHA-256 over the diagnostics' and the contracts' Python sources (names and bytes), read
    once per process (None: a source could not be read, no cache). A caller that can (the command
    line) reads them before it imports the diagnostics: a source edited in between then only costs
    a miss, never a ranking of the old code filed under the new code's key."""
    global _code_digest
    if _code_digest is None:
        h = hashlib.sha256()
        try:
            for d in SOURCE_DIRS:
                for p in sorted(d.glob("*.py")):
                    h.update(f"{d.name}/{p.name}\0".encode())
                    h.update(p.read_bytes())
                    h.update(b"\0")
        except OSError as exc:
            log.debug("diagnose cache: cannot read the sources (%s)", exc)
            return None
        _code_digest = h.hexdigest()
    return _code_digest


def log_digest(lg: Any) -> str:
    """SHA-256 of a DutLog's content: every column (dtype, shape, values) and its header lines."""
    h = hashlib.sha256()
    for name in ("time_s", "acc_g", "temp_c", "lamp", "position", "ref_dir"):
        arr = getattr(lg, name, None)
        if arr is None:
            h.update(f"{name}:none;".encode())
            continue
        a = np.ascontiguousarray(arr)
        h.update(f"{name}:{a.dtype.str}:{a.shape};".encode())
        h.update(a)  # its bytes (C order), without a copy of them
    h.update(json.dumps(sorted((str(k), str(v)) for k, v in lg.meta.items())).encode())
    return h.hexdigest()


class _Unstable(Exception):
    """A part of the question has no description that is the same in every process: no cache."""


def _stable_repr(value: Any) -> str:
    """repr(), with sets in sorted order; an object shown by its address is refused (_Unstable)."""
    if isinstance(value, (set, frozenset)):
        return "{" + ", ".join(sorted(_stable_repr(v) for v in value)) + "}"
    text = repr(value)
    if " at 0x" in text:
        raise _Unstable(text[:80])
    return text


_SKIP_ATTRS = {"__module__", "__dict__", "__weakref__", "__doc__", "__qualname__", "__annotations__"}


def _source_file(value: Any) -> str | None:
    """The file a function (method, static/class method, property) was defined in."""
    value = getattr(value, "__func__", value)
    if isinstance(value, property):
        value = value.fget
    code = getattr(value, "__code__", None)
    return None if code is None else code.co_filename


def effect_digest(effect: Any) -> str:
    """SHA-256 of what defines an effect: its classes' names and data attributes, the instance's
    own attributes, and the content of every source file its methods were defined in (the
    methods, the helpers beside them: a user's --effects-file, or station/diagnostics/effects.py)."""
    h = hashlib.sha256()
    files: set[str] = set()
    for klass in type(effect).__mro__:
        if klass is object:
            continue
        h.update(f"class {klass.__qualname__};".encode())
        for name, value in sorted(vars(klass).items()):
            if name in _SKIP_ATTRS:
                continue
            f = _source_file(value)
            if f is not None:
                files.add(f)
                h.update(f"{name}=<code in {Path(f).name}>;".encode())
            elif not callable(value):
                h.update(f"{name}={_stable_repr(value)};".encode())
    for name, value in sorted(vars(effect).items()):
        h.update(f"self.{name}={_stable_repr(value)};".encode())
    for f in sorted(files):
        h.update(f"file {Path(f).name}:{_file_digest(f)};".encode())
    return h.hexdigest()


def _file_digest(path: str) -> str:
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError:  # no file to read back (code made by exec, a deleted file)
        raise _Unstable(path) from None


def cache_key(logs: list[Any], names: list[str], basis: str, seg: Any, version: str) -> dict:
    """The question a cached ranking answers, as a JSON-able dict (raises _Unstable)."""
    import scipy

    from station.diagnostics.effects import get_effect

    code = code_digest()
    if code is None:
        raise _Unstable("the sources cannot be read")
    return {
        "format": FORMAT,
        "software": version,
        "code": code,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "logs": [log_digest(lg) for lg in logs],
        "candidates": [[n, effect_digest(get_effect(n))] for n in names],
        "basis": basis,
        "segmentation": _stable_repr(seg),
    }


def _key_hex(key: dict) -> str:
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()


# ---- the files ------------------------------------------------------------------------------------
# The file and key found by the last load(), for the store() that follows a miss in the same
# diagnose() call (the logs are the same objects: the key is not computed twice).
_pending: tuple[tuple, Path, dict] | None = None


def _lookup(logs: list[Any], names: list[str], basis: str, seg: Any) -> tuple[Path, dict] | None:
    """The cache file and key of a question (None: cache off, or no stable key)."""
    global _pending
    settings = _SETTINGS.get()
    if settings is None:
        return None
    question = (tuple(logs), tuple(names), basis, repr(seg), settings)
    pending, _pending = _pending, None
    if pending is not None and len(pending[0][0]) == len(logs) and \
            all(a is b for a, b in zip(pending[0][0], logs)) and pending[0][1:] == question[1:]:
        return pending[1], pending[2]
    try:
        key = cache_key(logs, names, basis, seg, settings.version)
    except Exception as exc:  # noqa: BLE001 - no key (an unstable part, an unknown candidate): no cache;
        log.debug("diagnose cache: no key (%s: %s)", type(exc).__name__, exc)  # the ranking says what is wrong
        return None
    path = settings.directory / (_key_hex(key) + SUFFIX)
    _pending = (question, path, key)  # for the store() after a miss; any other lookup drops it
    return path, key


def _forget() -> None:
    global _pending
    _pending = None


def _owned(st: os.stat_result) -> bool:
    return st.st_uid == os.getuid() and not st.st_mode & 0o022


def _trusted_dir(directory: Path) -> bool:
    """The folder is the user's own and nobody else may write into it (POSIX)."""
    return not hasattr(os, "getuid") or _owned(os.stat(directory))


def _trusted(path: Path) -> bool:
    """The file (not a symbolic link) and its folder are the user's own, writable by nobody else."""
    return not hasattr(os, "getuid") or (_trusted_dir(path.parent) and _owned(os.lstat(path)))


def load(logs: list[Any], names: list[str], basis: str, seg: Any, kind: type) -> Any | None:
    """The cached ranking of this question (an instance of `kind`), or None: cache off, no file,
    or a file that is not exactly this question's (ignored; the next store replaces it)."""
    found = _lookup(logs, names, basis, seg)
    if found is None:
        return None
    path, key = found
    try:
        if not path.is_file() or not _trusted(path):
            return None
        size = path.stat().st_size
        if size > MAX_TOTAL_BYTES:
            return None
        with open(path, "rb") as f:  # read as a stream: a long log's ranking is hundreds of MB
            obj = _read(f, key)
        if not isinstance(obj, kind):
            raise ValueError(f"holds a {type(obj).__name__}, not a {kind.__name__}")
        data = getattr(obj, "data", None)
        if not isinstance(data, list) or [getattr(d, "serial", None) for d in data] != \
                [lg.serial or "dut" for lg in logs]:
            raise ValueError("holds the ranking of other logs")
        with contextlib.suppress(OSError):
            os.utime(path)  # recently used: evicted last
        _forget()
        return obj
    except Exception as exc:  # noqa: BLE001 - a cache file is never trusted: any failure is a miss
        log.debug("diagnose cache: %s ignored (%s: %s)", path, type(exc).__name__, exc)
        return None


COPY_BYTES = 1 << 20  # a cache file is hashed, copied and read this much at a time


def _read(f: BinaryIO, key: dict) -> Any:
    """The object of a cache file open at its start: the header checked, then the payload's length
    and SHA-256 (a pass over it a MB at a time), and only then unpickled, from the file (no copy of
    the payload in memory beside the object it makes)."""
    head = f.read(len(MAGIC) + MAX_HEADER_BYTES + 1)
    if not head.startswith(MAGIC):
        raise ValueError("not a diagnose cache file")
    end = head.find(b"\n", len(MAGIC), len(MAGIC) + MAX_HEADER_BYTES)
    if end < 0:
        raise ValueError("no header")
    header = json.loads(head[len(MAGIC):end])
    if header.get("format") != FORMAT or header.get("key") != key:
        raise ValueError("another format or question")
    f.seek(end + 1)
    digest, n = hashlib.sha256(), 0
    while chunk := f.read(COPY_BYTES):
        digest.update(chunk)
        n += len(chunk)
    if n != header.get("payload_bytes") or digest.hexdigest() != header.get("payload_sha256"):
        raise ValueError("truncated or corrupted")
    f.seek(end + 1)
    return pickle.load(f)


class _Hashing:
    """A file writer that hashes and counts what it writes (the payload, written as pickled)."""

    def __init__(self, f: BinaryIO) -> None:
        self.f, self.digest, self.n = f, hashlib.sha256(), 0

    def write(self, b: bytes) -> int:
        self.digest.update(b)
        self.n += len(memoryview(b).cast("B"))
        return self.f.write(b)


def store(obj: Any, logs: list[Any], names: list[str], basis: str, seg: Any) -> Path | None:
    """Write the ranking of this question (cache on); returns the file, None when not written
    (cache off, no stable key, a folder that cannot be written, an object pickle refuses)."""
    found = _lookup(logs, names, basis, seg)
    if found is None:
        return None
    path, key = found
    _forget()
    tmp: str | None = None
    body: str | None = None
    try:
        path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        if not _trusted_dir(path.parent):  # a file there would never be read
            return None
        # the payload is pickled straight into a file (hashed as it goes), then copied behind the
        # header, a MB at a time: never the whole pickle in memory beside the object
        fd, body = tempfile.mkstemp(prefix=".tmp-", suffix=".body", dir=path.parent)
        with os.fdopen(fd, "w+b") as pf:
            w = _Hashing(pf)
            pickle.dump(obj, w, protocol=pickle.HIGHEST_PROTOCOL)
            header = json.dumps({"format": FORMAT, "key": key, "payload_bytes": w.n,
                                 "payload_sha256": w.digest.hexdigest()}, sort_keys=True).encode()
            fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=SUFFIX, dir=path.parent)
            with os.fdopen(fd, "wb") as f:
                f.write(MAGIC + header + b"\n")
                pf.seek(0)
                while chunk := pf.read(COPY_BYTES):
                    f.write(chunk)
        os.replace(tmp, path)
        tmp = None
    except Exception as exc:  # noqa: BLE001 - a cache that cannot be written is no cache, never an error
        log.debug("diagnose cache: not written to %s (%s: %s)", path, type(exc).__name__, exc)
        return None
    finally:
        for leftover in (tmp, body):
            if leftover is not None:
                with contextlib.suppress(OSError):
                    os.unlink(leftover)
    _evict(path.parent, keep=path)
    return path


def _evict(directory: Path, keep: Path) -> None:
    """Delete the least recently used files beyond MAX_ENTRIES or MAX_TOTAL_BYTES."""
    try:
        entries = []
        for p in directory.glob("*" + SUFFIX):
            if p.name.startswith(".tmp-"):
                continue
            st = p.stat()
            entries.append((st.st_mtime, st.st_size, p))
        entries.sort(reverse=True)  # newest first
        total = 0
        for k, (_, size, p) in enumerate(entries):
            total += size
            if p != keep and (k >= MAX_ENTRIES or total > MAX_TOTAL_BYTES):
                with contextlib.suppress(OSError):
                    p.unlink()
    except OSError:
        pass


__all__ = ["enabled", "load", "store", "default_directory", "cache_key", "code_digest", "log_digest",
           "effect_digest", "FORMAT", "ENV"]
