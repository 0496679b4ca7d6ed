"""`station simulate`: logs of simulated DUTs (design 5.1) plus their true parameters (truth.json).

    station simulate --out DIR [--duts N] [--profile NAME] [--sensor S] [--effect NAME ...] [--seed S]
                     [--noise realistic|white|lis3dsh|adxl355]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from contracts.types import StationError

DEFAULT_DUTS = 4


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from drivers.sim.physics import HIDDEN_EFFECTS, SENSORS
    from drivers.sim.profiles import PROFILES

    parser.add_argument("--out", required=True, metavar="DIR", help="directory for <serial>.csv logs and truth.json")
    parser.add_argument("--duts", type=int, default=DEFAULT_DUTS, metavar="N", help=f"number of DUTs (default {DEFAULT_DUTS})")
    parser.add_argument("--profile", default="fast-thermal", metavar="NAME", help=f"one of {', '.join(PROFILES)} (default fast-thermal)")
    parser.add_argument("--sensor", default="LIS3DSH", metavar="S", help=f"one of {', '.join(SENSORS)} (default LIS3DSH)")
    parser.add_argument(
        "--effect",
        action="append",
        default=[],
        metavar="NAME",
        help=f"switch on a hidden effect (repeatable, or comma separated): {', '.join(HIDDEN_EFFECTS)}",
    )
    from drivers.sim.physics import DEFAULT_NOISE, NOISE_NAMES

    parser.add_argument("--noise", default=DEFAULT_NOISE, metavar="NAME",
                        help=f"noise model: {', '.join(NOISE_NAMES)} (default {DEFAULT_NOISE}: bias random walk and "
                             f"flicker of the sensor's class; white = the ideal part)")
    parser.add_argument("--seed", type=int, default=0, help="population and noise seed (default 0)")
    parser.add_argument("--odr", type=float, default=None, metavar="HZ", help="output data rate (default: the sensor's)")
    parser.add_argument("--quiet", action="store_true", help="no progress line")


def run(args: argparse.Namespace) -> int:
    from drivers.sim.physics import SENSORS, check_effects, draw_population, noise_model, population_to_json
    from drivers.sim.profiles import PROFILES, run_profile, step_table
    from drivers.sim.world import EnvConfig, SimWorld
    from contracts.logfile import write_log

    if args.profile not in PROFILES:
        raise StationError(f"unknown profile {args.profile!r} (known: {', '.join(PROFILES)})")
    if args.sensor not in SENSORS:
        raise StationError(f"unknown sensor {args.sensor!r} (known: {', '.join(SENSORS)})")
    if args.duts < 1:
        raise StationError(f"--duts must be at least 1 (got {args.duts})")
    if args.odr is not None and args.odr <= 0:
        raise StationError(f"--odr must be positive (got {args.odr:g})")
    nm = noise_model(args.noise, args.sensor)  # validates the name
    effects = check_effects([e.strip() for item in args.effect for e in item.split(",") if e.strip()])
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise StationError(f"{out}: exists and is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StationError(f"{out}: cannot create directory ({exc.strerror})") from None

    truths = draw_population(args.duts, args.seed, sensor=args.sensor, effects=effects)
    env = EnvConfig()
    world = SimWorld(truths, env=env, odr_hz=args.odr, seed=args.seed, noise=args.noise)
    t0 = time.perf_counter()
    progress, done = _progress(args.quiet, args.profile)
    try:
        logs = run_profile(world, args.profile, progress=progress)
    finally:
        done()
    sim_s = time.perf_counter() - t0
    from contracts.filenames import safe_path

    files = {log.serial: safe_path(out, log.serial, ".csv") for log in logs}  # a serial is data, never a path
    for log in logs:
        write_log(files[log.serial], log)
    doc = population_to_json(
        truths,
        profile=args.profile,
        sensor=args.sensor,
        seed=args.seed,
        effects=list(effects),
        noise={"requested": args.noise, **nm.to_json()},
        odr_hz=world.odr_hz,
        env=env.to_json(),
        steps=step_table(args.profile),
        logs={serial: p.name for serial, p in files.items()},
    )
    (out / "truth.json").write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    n = len(logs[0]) if logs else 0
    print(
        f"wrote {len(logs)} logs ({n} samples, {n / world.odr_hz / 60:.0f} min each, profile {args.profile}, "
        f"effects {','.join(effects) or 'none'}, noise {nm.name}) and truth.json to {out} "
        f"[simulated in {sim_s:.1f} s, total {time.perf_counter() - t0:.1f} s]"
    )
    return 0


def _progress(quiet: bool, label: str):
    """A rich progress line on stderr when it is a terminal; no-op otherwise."""
    if quiet or not sys.stderr.isatty():
        return None, lambda: None
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    bar = Progress(TextColumn(f"simulate {label}"), BarColumn(), TextColumn("{task.fields[sim]}"), TimeRemainingColumn(), transient=True)
    bar.start()
    task = bar.add_task(label, total=1.0, sim="")

    def update(done_s: float, total_s: float) -> None:
        bar.update(task, completed=done_s / total_s if total_s else 1.0, sim=f"{done_s / 60:.0f}/{total_s / 60:.0f} sim min")

    return update, bar.stop
