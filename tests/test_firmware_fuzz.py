"""The board firmware's portable core under libFuzzer (firmware/fuzz/, issue 42), four input paths.

Why: the core parses everything a station, a CAN bus, its own flash and the simulator's sensor
bridge hand it, on a board with no memory protection; a crash there is a board that stops, and a
NaN that reaches the calibration is a board that streams garbage while reporting success. Each path
is fuzzed for FW_FUZZ_S seconds (default 30; the four run at the same time) with ASan and UBSan, from
seeds written from the protocol at test time (firmware/fuzz/gen_seeds.py), and must end with no crash,
no sanitizer report and no invariant violation (fuzz_common.h: no non-finite coefficient applied,
nothing written to NVM that fw_nvm_decode would not read back as valid, every frame sent well formed).

A fuzz run that cannot fail proves nothing, so two tests break the harness on purpose:
- fuzz_selftest puts a NaN and an infinity into every float of fw_cal_t and expects the check to
  name each, and hands the NVM and frame checks images and frames they must refuse;
- a deliberately broken build (FW_FUZZ_SELFTEST: the command parsers' fw_f32_finite wrapped to say
  "finite" for everything) must fail the same runner on the protocol's own `$CALW,nan,...` seed,
  with a reproducer that fails the broken build and passes the real one (which answers
  `E,CALW,non-finite value`).
Skipped, with the reason, where clang or its libFuzzer runtime is missing (STATION_REQUIRE_FIRMWARE=1:
failed instead); scripts/test.sh installs both.
"""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from drivers.sim.firmware_build import BUILD_DIR, FIRMWARE_DIR, build

TARGETS = ("serial", "can", "nvm", "bridge")
FUZZ_S = int(os.environ.get("FW_FUZZ_S", "30"))
RUNNER = FIRMWARE_DIR / "fuzz" / "run_fuzz.py"
BROKEN_DIR = "build/fuzz-selftest"  # relative to firmware/, like make's own paths


def _libfuzzer_missing(tmp: Path) -> str | None:
    """Why libFuzzer cannot be used here (None when a trivial fuzz target links)."""
    if shutil.which("clang") is None:
        return "clang not on PATH"
    src = tmp / "probe.c"
    src.write_text("#include <stddef.h>\n#include <stdint.h>\n"
                   "int LLVMFuzzerTestOneInput(const uint8_t *d, size_t n) { (void)d; (void)n; return 0; }\n")
    proc = subprocess.run(["clang", "-fsanitize=fuzzer,address,undefined", "-o", str(tmp / "probe"), str(src)],
                          capture_output=True, text=True)
    return None if proc.returncode == 0 else f"clang cannot link -fsanitize=fuzzer: {proc.stderr.strip()[-300:]}"


def _need_libfuzzer(tmp: Path) -> None:
    why = _libfuzzer_missing(tmp)
    if why:
        if os.environ.get("STATION_REQUIRE_FIRMWARE") == "1":
            pytest.fail(f"libFuzzer missing: {why} (scripts/test.sh installs clang and libclang-rt-14-dev)")
        pytest.skip(f"libFuzzer missing: {why}")


def _run(bin_dir: Path, work: Path, seconds: int, targets: tuple[str, ...]) -> tuple[int, str, list[dict[str, Any]]]:
    """The runner `make fuzz` uses, all targets at once at a lower priority (four fuzzers on a CI
    machine's two cores would otherwise starve the browser tests beside them); its exit code,
    output and per-target figures."""
    summary = work / "summary.json"
    proc = subprocess.run([sys.executable, str(RUNNER), "--bin-dir", str(bin_dir), "--work-dir", str(work),
                           "--seconds", str(seconds), "--targets", ",".join(targets), "--parallel", "--nice", "10",
                           "--json", str(summary)], capture_output=True, text=True, timeout=seconds + 120)
    rows = json.loads(summary.read_text()) if summary.exists() else []
    return proc.returncode, proc.stdout + proc.stderr, rows


@pytest.fixture(scope="module")
def fuzz_campaign(tmp_path_factory: pytest.TempPathFactory) -> tuple[int, str, dict[str, dict[str, Any]]]:
    """Build the harness and fuzz the four paths once, in parallel, for FW_FUZZ_S seconds."""
    tmp = tmp_path_factory.mktemp("fuzz")
    _need_libfuzzer(tmp)
    build("fuzz-build")
    rc, out, rows = _run(BUILD_DIR / "fuzz", tmp / "run", FUZZ_S, TARGETS)
    print(out)
    return rc, out, {r["target"]: r for r in rows}


@pytest.mark.timeout(FUZZ_S + 400)
@pytest.mark.parametrize("target", TARGETS)
def test_fuzz_path_has_no_crash_and_no_invariant_violation(
        fuzz_campaign: tuple[int, str, dict[str, dict[str, Any]]], target: str) -> None:
    rc, out, rows = fuzz_campaign
    r = rows.get(target)
    assert r is not None, out
    # it really fuzzed: libFuzzer ran inputs beyond the seeds and reached code (a harness that
    # returns early would show a handful of runs and a coverage near zero)
    assert r["crashes"] == 0 and r["violations"] == 0 and r["exit_code"] == 0, (r["artifacts"], out)
    assert r["runs"] >= 200, r
    assert r["cov"] >= 150 and r["cov"] <= r["edges"], r
    assert r["seconds"] >= FUZZ_S * 0.9, r  # ran its whole time, did not stop early


@pytest.mark.timeout(300)
def test_invariant_checks_flag_nan_in_every_calibration_float(tmp_path: Path) -> None:
    _need_libfuzzer(tmp_path)
    build("fuzz-build")
    proc = subprocess.run([str(BUILD_DIR / "fuzz" / "fuzz_selftest")], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and "SELFTEST OK" in proc.stdout, proc.stdout + proc.stderr


@pytest.mark.timeout(400)
def test_broken_finiteness_check_fails_the_fuzz_run(tmp_path: Path) -> None:
    _need_libfuzzer(tmp_path)
    build("fuzz-build")
    with open(BUILD_DIR / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        proc = subprocess.run(["make", "-C", str(FIRMWARE_DIR), f"{BROKEN_DIR}/fuzz_serial",
                               f"FUZZ_DIR={BROKEN_DIR}", "FUZZ_DEFS=-DFW_FUZZ_SELFTEST",
                               "FUZZ_LDFLAGS=-Wl,--wrap=fw_f32_finite"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    broken = FIRMWARE_DIR / BROKEN_DIR

    rc, out, rows = _run(broken, tmp_path / "run", 5, ("serial",))
    assert rc != 0, out  # what fails `make fuzz`
    (r,) = rows
    assert r["crashes"] >= 1 and r["violations"] >= 1, (r, out)
    assert "FW_FUZZ INVARIANT VIOLATION" in out and "non-finite" in out, out
    repro = Path(r["artifacts"][0])
    assert repro.exists(), r

    # the reproducer fails the broken build again, and the real core refuses the same input
    again = subprocess.run([str(broken / "fuzz_serial"), str(repro)], capture_output=True, text=True, timeout=60)
    assert again.returncode != 0 and "FW_FUZZ INVARIANT VIOLATION" in again.stderr, again.stderr[-2000:]
    real = subprocess.run([str(BUILD_DIR / "fuzz" / "fuzz_serial"), str(repro)], capture_output=True, text=True,
                          timeout=60)
    assert real.returncode == 0, real.stderr[-2000:]
