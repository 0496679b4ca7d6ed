"""The judged measurements in words, with units as an engineer writes them: "TDB x (mg/°C)".

A parameter is `measurement` or `measurement:axis` (station/records/spc.py). The names here cover
every measurement the verdict checks use (station/decisions/verdicts.py builds them,
station/decisions/limits.py limits them; tests/test_spc.py proves no name is missing), so the
Records view never shows a raw `tdb_mg_per_c:x`. An unknown name (a site's own measurement) is
still shown in words: underscores as spaces, with the unit its checks carry.
"""

from __future__ import annotations

# measurement -> (words, unit as shown). The unit strings of the checks ("mg/C", "ug/sqrt(Hz)") are
# ASCII for logs and CSV; a person reads °C, µg and √Hz.
WORDS: dict[str, tuple[str, str]] = {
    "tdb_mg_per_c": ("TDB", "mg/°C"),
    "tdsf_ppm_per_c": ("TDSF", "ppm/°C"),
    "drift_error_fs_pct": ("drift error E_FS", "%FS"),
    "drift_error_mg": ("drift error", "mg"),
    "bow_mg": ("curvature (bow)", "mg"),
    "ramp_residual_rms_mg": ("ramp residual RMS", "mg"),
    "fit_agreement_tdb_mg_per_c": ("streaming vs offline TDB", "mg/°C"),
    "fit_agreement_tdsf_ppm_per_c": ("streaming vs offline TDSF", "ppm/°C"),
    "noise_ug_per_sqrt_hz": ("noise density", "µg/√Hz"),
    "lost_samples_pct": ("lost samples", "%"),
    "link_errors": ("link errors", "frames"),
    "sfem_bias_mg": ("SFEM bias", "mg"),
    "sfem_scale_error_pct": ("SFEM scale error", "%"),
    "sfem_heldout_rmse_mg": ("SFEM held-out |a| - 1 g RMSE", "mg"),
    "sfem_residual_ratio": ("SFEM residual / noise", "x noise"),
    "verified_drift_error_fs_pct": ("verified drift error E_FS", "%FS"),
    "verify_failed_axes": ("axes failing verification", "axes"),
    "program_crc_match": ("readback CRC equal to written", "1 = yes"),
    "compensation_on": ("compensation on", "1 = yes"),
}

_UNIT_WORDS = {"mg/C": "mg/°C", "ppm/C": "ppm/°C", "ug/sqrt(Hz)": "µg/√Hz", "ug": "µg"}


def split(parameter: str) -> tuple[str, str | None]:
    """('tdb_mg_per_c', 'x') from 'tdb_mg_per_c:x'; axis None for a per-DUT measurement."""
    m, _, ax = parameter.partition(":")
    return m, (ax or None)


def unit_words(measurement: str, check_unit: str = "") -> str:
    """The unit as shown: the table's, else the check's own unit made readable."""
    if measurement in WORDS:
        return WORDS[measurement][1]
    return _UNIT_WORDS.get(check_unit, check_unit)


def words(parameter: str) -> str:
    """'TDB x' (no unit): for the failure Pareto, where the count is the number."""
    m, ax = split(parameter)
    w = WORDS[m][0] if m in WORDS else m.replace("_", " ").strip() or "unnamed"
    return f"{w} {ax}" if ax else w


def label(parameter: str, check_unit: str = "") -> str:
    """'TDB x (mg/°C)', 'TDSF z (ppm/°C)', 'lost samples (%)'."""
    m, _ax = split(parameter)
    u = unit_words(m, check_unit)
    return f"{words(parameter)} ({u})" if u else words(parameter)


__all__ = ["WORDS", "split", "unit_words", "words", "label"]
