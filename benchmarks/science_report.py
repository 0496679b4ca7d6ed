"""The science's acceptance figures, computed on the real pipeline (simulator -> logs ->
station.science) and on the real imucal session: fast-thermal TDB/TDSF against the simulator's
truth, streaming vs offline TD_i (martinez2022 Table 5), the six-position chamber test's drift error
before and after compensation (martinez2022 Table 7), SFEM on sfem-24 data (sensors2023 Table 6),
the station's fit of the imucal session against its reference calibration, and the streaming
calibrator's throughput.

    .venv/bin/python benchmarks/science_report.py [--skip-bench]

The computations are the acceptance tests' own (tests/test_science_acceptance.py,
tests/test_imucal_real_data.py); this script prints them. Throughput is benchmarks/bench_streaming.py
(run as a subprocess on one core). No assertion here: the tests assert.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, os.path.join(ROOT, "tests"))
sys.path.insert(0, ROOT)

import test_imucal_real_data as imu  # noqa: E402
import test_science_acceptance as acc  # noqa: E402
from station.science.thermal_model import drift_error_fs_pct  # noqa: E402


def _h(title: str) -> None:
    print(f"\n== {title} " + "=" * max(0, 90 - len(title)))


def thermal_section(th: acc.ThermalAcceptance, label: str) -> None:
    n_ok = sum(r is not None for r in th.results)
    print(f"{label}: {n_ok}/{len(th.results)} DUTs calibrated; step durations {[round(d / 60, 1) for d in th.step_durations_s]} min")
    for e in {e for e in th.errors if e}:
        print(f"  not calibrated ({th.errors.count(e)} DUT): {e}")
    print(f"  {'method':<10} {'axes pass':>10} {'TDB<0.03':>9} {'TDSF<40':>8} {'worst TDB err':>14} {'worst TDSF err':>15} {'RMS TDB err':>12} {'RMS TDSF err':>13}")
    for method in ("streaming", "offline"):
        eb, es = th.axis_errors(method)
        fin = np.isfinite(eb)
        print(
            f"  {method:<10} {th.pass_fraction(method):>10.1%} {np.mean(eb < acc.TDB_TOL_MG_PER_C):>9.1%} {np.mean(es < acc.TDSF_TOL_PPM_PER_C):>8.1%} "
            f"{eb[fin].max():>9.4f} mg/C {es[fin].max():>9.2f} ppm/C {np.sqrt(np.mean(eb[fin] ** 2)):>7.4f} mg/C {np.sqrt(np.mean(es[fin] ** 2)):>7.2f} ppm/C"
        )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--skip-bench", action="store_true", help="do not run bench_streaming.py")
    args = ap.parse_args()
    t_all = time.perf_counter()

    _h(f"1. Fast-thermal, {acc.N_DUTS} simulated LIS3DSH DUTs (seed {acc.SEED}); truth from the simulator")
    t0 = time.perf_counter()
    th = acc.fast_thermal_acceptance()
    print(f"targets: TDB within {acc.TDB_TOL_MG_PER_C} mg/C and TDSF within {acc.TDSF_TOL_PPM_PER_C:g} ppm/C on >= {acc.PASS_FRACTION:.0%} of axes, each method")
    thermal_section(th, "closed loop (station sequencer rule: a step ends when every DUT has its segment)")
    ol = acc.open_loop_fast_thermal()
    thermal_section(ol, "open loop (`station simulate` fixed durations)")
    print(f"  ({time.perf_counter() - t0:.1f} s)")

    _h("2. Streaming vs offline TD_i (martinez2022 Table 5: within 1 %)")
    pairs = th.td_pairs()
    diff = np.abs(pairs[:, 0] - pairs[:, 1])
    rel = diff / np.abs(pairs[:, 1])
    small = acc.TD_REL_TOL * np.abs(pairs[:, 1]) < pairs[:, 2]
    print(f"{pairs.shape[0]} TD_i (32 DUTs x 3 axes x 2 orientations)")
    print(f"  |TD_i| large enough for 1 % to exceed the streaming noise: {np.sum(~small)}; max rel diff {rel[~small].max():.3%}, median {np.median(rel[~small]):.3%}")
    print(
        f"  |TD_i| < {pairs[small, 2].max() / acc.TD_REL_TOL:.3f} mg/C: {np.sum(small)}; max |diff| {diff[small].max():.4f} mg/C "
        f"(3-sigma streaming noise {pairs[small, 2].min():.4f}..{pairs[small, 2].max():.4f} mg/C); "
        f"{np.sum(rel > acc.TD_REL_TOL)} of all {pairs.shape[0]} differ by > 1 % (all with |TD_i| < 0.1 mg/C)"
    )
    print(f"  over all TD_i: max |diff| {diff.max():.4f} mg/C, max rel diff {rel.max():.2%}")

    _h("3. Six-position chamber test (-10..60 C, 5 steps x 6 orientations), compensated with the fast-thermal values")
    t0 = time.perf_counter()
    sections = acc.six_position_sections(th.truths, acc.SEED)
    print("martinez2022 Table 7 (real sensors): 42.77 mg -> 12.18 mg average")
    print(f"  {'parameters':<12} {'E avg before':>13} {'E avg after':>12} {'after/before':>13} {'E max before':>13} {'E max after':>12}   (%FS avg before -> after)")
    for method in ("offline", "streaming"):
        b, a = acc.drift_errors(sections, th.params(method))
        print(
            f"  {method:<12} {b.mean():>10.2f} mg {a.mean():>9.3f} mg {a.mean() / b.mean():>12.2%} {b.max():>10.2f} mg {a.max():>9.3f} mg"
            f"   ({drift_error_fs_pct(b.mean()):.2f} % -> {drift_error_fs_pct(a.mean()):.3f} %)"
        )
    print(f"  (E per DUT x orientation x axis = {len(sections) * 6 * 3} values; sections = last {acc.HOLD_TAIL_S / 60:g} min of each hold; {time.perf_counter() - t0:.1f} s)")
    print("  note: hidden effects are off in this population, so the compensated residual is the noise/quantisation floor;")
    print("  the paper's 12 mg residual comes from what eq. 1 does not model on real parts.")

    _h("4. SFEM on simulated sfem-24 data (sensors2023 Table 1 plan, 5 chamber steps), the step nearest 25 C")
    t0 = time.perf_counter()
    cases = acc.sfem_acceptance(th.truths, acc.SEED)
    before = np.array([c.rmse_before_mg for c in cases])
    after = np.array([c.rmse_after_mg for c in cases])
    print("sensors2023 Table 6: ~45 mg -> ~0.2 mg")
    print(f"  |a|-1 g RMSE before: mean {before.mean():.2f} mg (min {before.min():.2f}, max {before.max():.2f})")
    print(f"  |a|-1 g RMSE after:  mean {after.mean():.4f} mg (max {after.max():.4f})")
    units = {"b": ("mg", 1e3), "scale": ("ppm", 1e6), "alpha": ("mrad", 1e3), "rotvec_rad": ("mrad", 1e3), "A": ("ppm", 1e6)}
    print(f"  parameter errors vs the truth at the step's die temperature, {len(cases)} DUTs (tolerance {acc.SFEM_SIGMA_K:g} sigma + floor):")
    n_fail = 0
    for k, (u, f) in units.items():
        err = np.concatenate([np.abs(c.err[k]).ravel() for c in cases]) * f
        sig = np.concatenate([c.sigma[k].ravel() for c in cases]) * f
        z = np.concatenate([c.z[k].ravel() for c in cases])
        ok = all(np.all(np.abs(c.err[k]) < c.tol[k]) for c in cases)
        n_fail += not ok
        print(f"    {k:<11} max |err| {err.max():9.4f} {u:<4} median sigma {np.median(sig):9.4f} {u:<4} max |z| {z.max():5.2f}  RMS z {np.sqrt(np.mean(z ** 2)):5.2f}  {'within' if ok else 'OUTSIDE'}")
    print("  (rotvec: the station's default 1 deg fixture assumption sets its sigma; the simulated fixture is exact)")
    print(f"  ({time.perf_counter() - t0:.1f} s)")

    _h("5. Real data: imucal six-position session (raw counts), station fit vs example_cal.json")
    fig = imu.imucal_figures()
    print(f"  positions {list(imu.PARTS)}, samples {fig['n_samples'].tolist()}, sigma of each mean {np.round(fig['sigma_mean_mg'], 3).tolist()} mg")
    print(f"  {'calibration':<44} {'direction RMSE':>15} {'RMS norm err':>13}")
    print(f"  {'reference (imucal Ferraris, example_cal.json)':<44} {fig['rmse_dir_reference_mg']:>12.4f} mg {fig['norm_reference_mg']:>10.4f} mg")
    print(f"  {'station reference-direction fit (1 deg)':<44} {fig['rmse_dir_station_mg']:>12.4f} mg {fig['norm_station_mg']:>10.4f} mg")
    print(f"  {'fit trusting the directions (1e-4 deg)':<44} {fig['rmse_dir_trusted_mg']:>12.4f} mg {fig['norm_trusted_mg']:>10.4f} mg")
    gap = fig["rmse_dir_station_mg"] - fig["rmse_dir_reference_mg"]
    print(f"  station - reference direction RMSE: {gap:+.4f} mg ({gap / fig['rmse_dir_reference_mg']:+.2%})")
    print(f"  direction residual per position (deg): {np.round(fig['direction_residual_deg'], 3).tolist()}")
    s = fig["session"]
    for name, res in (("station", fig["fit"].apply(s.means) - imu.REFS), ("reference", fig["reference"].apply_g(s.means) - imu.REFS)):
        print(f"  {name:<9} calibrated - reference direction (mg), {'/'.join(imu.PARTS)}: {np.round(res * 1e3, 2).tolist()}")
    print("  (antipodal pairs leave the same vector: an even-order term / fixture wedge no affine calibration removes)")
    f = fig["fit"]
    print(f"  bias (counts) {np.round(f.b, 2).tolist()} +- {np.round(f.sigma['b'], 2).tolist()}; antipodal-pair midpoints {np.round(fig['pair_midpoint_bias_counts'], 2).tolist()}")
    ref = fig["reference"]
    print(f"  reference b_a (counts) {np.round(ref.b, 2).tolist()}")
    st = imu.tilt_study(fig)
    print(
        f"  10 fixtures with 1 deg random direction tilts: bias shift max {max(st['joint_bias_shift_mg']):.3f} mg "
        f"(fit trusting the directions: {max(st['trusted_bias_shift_mg']):.2f} mg); norm error max {max(st['joint_norm_mg']):.4f} mg "
        f"(trusting: {min(st['trusted_norm_mg']):.2f}..{max(st['trusted_norm_mg']):.2f} mg)"
    )
    print(f"  RMS of shift / fit sigma: bias {st['rms_z']['b']:.2f}, non-orthogonality {st['rms_z']['alpha']:.2f}, S of MCS {st['rms_z']['scale']:.2f}")

    if not args.skip_bench:
        _h("6. Streaming calibrator throughput (benchmarks/bench_streaming.py, one core); target >= 1,000,000 samples/s batched")
        env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
        out = subprocess.run([sys.executable, os.path.join(HERE, "bench_streaming.py")], env=env, capture_output=True, text=True, check=True)
        print(out.stdout.rstrip())
    print(f"\n(total {time.perf_counter() - t_all:.1f} s)")


if __name__ == "__main__":
    main()
