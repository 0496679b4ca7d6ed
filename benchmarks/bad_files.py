"""Bad files: every hostile log the tests know through `station calibrate`, one row each.

    .venv/bin/python benchmarks/bad_files.py [--nul-gb 2]

The files are tests/test_bad_files.py's (write_cases), written to a temporary folder; the NUL file
is a valid start followed by --nul-gb GB of holes (truncate: sparse, no disk). Each runs the real
command line in a subprocess under a small parent (run_measured), so the peak memory is the
command's own ru_maxrss. Prints: case | exit code | the one stderr line | peak memory MB | seconds.
Before the reader refused what is not text (contracts/logfile.py) and the checks bounded every
value (contracts/log_checks.py), the 2 GB NUL file took 12.7 GB and 93 s, and `ay_g = 1e308`
exited 0.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nul-gb", type=float, default=2.0, help="GB of NUL bytes after the valid start (default 2)")
    args = ap.parse_args()
    from test_bad_files import run_measured, write_cases

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        cases = write_cases(Path(tmp), nul_bytes=int(args.nul_gb * 1024**3))
        for name, (path, opts, want_rc, _) in cases.items():
            r = run_measured(["calibrate", path.name, "--json", *opts], cwd=path.parent)
            err = r["err"].splitlines()
            line = err[0] if len(err) == 1 else ("-" if not err else f"{len(err)} lines: {err[0]}")
            if name.startswith("NUL x "):
                name = f"NUL x {args.nul_gb:g} GB (sparse)"
            rows.append((name, str(r["rc"]) + ("" if r["rc"] == want_rc else f" (want {want_rc})"), line,
                         f"{r['peak_mb']:.0f}", f"{r['s']:.2f}"))
    head = ("case", "exit code", "the one line (stderr)", "peak memory MB", "seconds")
    widths = [max(len(x[k]) for x in (head, *rows)) for k in range(len(head))]
    for k, row in enumerate((head, *rows)):
        print(" | ".join(c.ljust(w) for c, w in zip(row, widths)).rstrip())
        if k == 0:
            print("-|-".join("-" * w for w in widths))
    return 0 if all(not r[1].endswith(")") for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
