"""Profiles are data: the sequencer's programs (design 4).

A step says where the plate is (position index), whether the lamp is on, the chamber set point,
what every DUT must log before the step ends, and a timeout in SAMPLE time (the boards' clock), so
a compressed-time replay behaves like the real station. A site adds its own profiles under
`[profiles.NAME]` in the config; a site profile with a built-in's name replaces it.

Each step's `require` names its kind, one registered object (station/steps: segment, static,
none, program, heat, and any kind a site registers): what every DUT must log before the step ends,
the kind's rules (checked here, so an unknown kind or a bad parameter is an error at load, never at
run time), its time estimate and the page's words for it.
A profile ends with program and verify by `with_program_verify(profile)`; `fast-thermal-verified`
is the built-in one. An SFEM profile may end with it too: boards that store the version-2 record
(caps `sfem3`) get the station's thermal SFEM as a cubic, read back, applied and verified on the
cool-down that follows (station/daemon/sfem_program.py); other boards are not programmed.

Issue 42 options (docs/profiles.md "Board options"):
  board_selfcal  (thermal profiles, default off) each board that runs its own calibrator (caps
                 `scal`) has it switched on before the thermal steps and read at their end; its
                 TDB/TDSF are compared with the station's (the verdict's check `board_selfcal_agrees`,
                 station/daemon/board_selfcal.py); a board without one: the check is not applicable.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from contracts.positions import POSITION_INDEX, POSITION_NAMES, SFEM24, SIX_POSITION
from station.science.verify import VerifyCriteria
from station.steps import Step as Step, kind_names

ANALYSES = ("thermal", "sfem", "none")
SFEM_VERIFY_DWELL_S = 1800.0  # an SFEM profile's verification cool-down, sample seconds (with_program_verify)


@dataclass(frozen=True)
class Profile:
    name: str
    steps: tuple[Step, ...]
    description: str = ""
    analysis: str = "none"  # what runs at the end: thermal (TDB/TDSF), sfem, none
    builtin: bool = field(default=True, compare=False)
    verify: VerifyCriteria = field(default_factory=VerifyCriteria)  # pass rule of a heat (verification) step
    # SFEM (analysis sfem): the temperature whose step the verdict judges and the thermal model is
    # centred on (None: contracts.types.T_REF_C, 25 C), and the fixture's reference direction error
    # where a step has too few positions to measure it (None: station.science.sfem's documented default)
    sfem_reference_temp_c: float | None = None
    sfem_ref_sigma_deg: float | None = None
    # the boards' own calibrators as a second opinion (module doc; thermal profiles only)
    board_selfcal: bool = False

    def __post_init__(self) -> None:
        if not self.steps:
            raise ValueError("a profile needs at least one step")
        if self.analysis not in ANALYSES:
            raise ValueError(f"analysis must be one of {ANALYSES}, not {self.analysis!r}")
        if self.sfem_ref_sigma_deg is not None and not self.sfem_ref_sigma_deg > 0:
            raise ValueError("sfem_ref_sigma_deg must be > 0")
        if self.board_selfcal and self.analysis != "thermal":
            raise ValueError("board_selfcal compares the boards' own TDB/TDSF with the station's: a thermal profile's option "
                             f"(this profile's analysis is {self.analysis!r})")
        known = kind_names()
        for i, s in enumerate(self.steps):
            if s.require not in known:
                raise ValueError(f"steps[{i}].require must be one of {known}, not {s.require!r}")
            if not 0 <= s.position < len(POSITION_NAMES):
                raise ValueError(f"steps[{i}].position {s.position} out of range")
            if s.timeout_s <= 0:
                raise ValueError(f"steps[{i}].timeout_s must be > 0")
            s.kind.check(self.steps, i, self.analysis)  # the kind's own rules (station/steps)

    @property
    def program_step(self) -> int | None:
        """Index of the program step, None if the profile does not end with program and verify."""
        return next((i for i, s in enumerate(self.steps) if s.require == "program"), None)

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "description": self.description,
            "analysis": self.analysis,
            "steps": [s.to_json() for s in self.steps],
            "program_verify": self.program_step is not None,
            "verify": self.verify.to_json() if self.program_step is not None else None,
            "board_selfcal": self.board_selfcal,
        }


def _pos(p: int | str) -> int:
    return POSITION_INDEX[p] if isinstance(p, str) else int(p)


def _fast_thermal() -> Profile:
    # Timeouts are generous maxima in sample time; a step normally ends as soon as every DUT has
    # logged its segment (~8 min of stable samples at 3.125 Hz after the plate settles).
    p, n = _pos("P"), _pos("N")
    return Profile(
        "fast-thermal",
        (
            Step("P ambient", p, lamp=False, require="segment", timeout_s=1800.0),
            Step("P hot", p, lamp=True, require="segment", timeout_s=3000.0),
            Step("N hot", n, lamp=True, require="segment", timeout_s=2400.0),
            Step("N ambient", n, lamp=False, require="segment", timeout_s=3600.0),
        ),
        description="martinez2022 fast thermal calibration: two orientations x two temperatures",
        analysis="thermal",
    )


def _six_position(temps_c: tuple[float, ...] = (25.0, 45.0, 65.0)) -> Profile:
    steps = []
    for t in temps_c:
        for k, name in enumerate(SIX_POSITION):
            steps.append(
                Step(
                    f"{name} @ {t:g} C",
                    _pos(name),
                    chamber_setpoint_c=t,
                    require="static",
                    settle_s=1800.0 if k == 0 else 30.0,
                    dwell_s=320.0,  # 1000 samples at 3.125 Hz
                    timeout_s=7200.0 if k == 0 else 1200.0,
                )
            )
    return Profile(
        "six-position",
        tuple(steps),
        description="martinez2022 reference: each axis up and down at several chamber temperatures",
        analysis="none",
    )


def _sfem24(temps_c: tuple[float, ...] = (25.0, 45.0, 65.0)) -> Profile:
    steps = []
    for t in temps_c:
        for k, name in enumerate(SFEM24):
            steps.append(
                Step(
                    f"{name} @ {t:g} C",
                    _pos(name),
                    chamber_setpoint_c=t,
                    require="static",
                    settle_s=1800.0 if k == 0 else 10.0,
                    dwell_s=64.0,  # 200 samples at 3.125 Hz
                    timeout_s=7200.0 if k == 0 else 600.0,
                )
            )
    return Profile(
        "sfem-24",
        tuple(steps),
        description="sensors2023 SFEM: the 24 positions of Table 1 at each temperature step",
        analysis="sfem",
    )


def _validation() -> Profile:
    steps = []
    for lamp in (False, True):
        label = "hot" if lamp else "ambient"
        for k, name in enumerate(SIX_POSITION):
            steps.append(
                Step(
                    f"{name} {label}",
                    _pos(name),
                    lamp=lamp,
                    require="static",
                    settle_s=900.0 if k == 0 else 30.0,
                    dwell_s=160.0,
                    timeout_s=2400.0 if k == 0 else 900.0,
                )
            )
    steps.append(Step("cool down", _pos("-z"), lamp=False, require="none", dwell_s=600.0, timeout_s=1200.0))
    return Profile(
        "validation",
        tuple(steps),
        description="check of calibrated DUTs: six positions at ambient and lamp-hot, for compensated-error review",
        analysis="none",
    )


def with_program_verify(
    profile: Profile,
    *,
    name: str | None = None,
    position: int | str | None = None,
    heat_c: float = 15.0,
    settle_s: float = 20.0,
    timeout_s: float = 2400.0,
    criteria: VerifyCriteria | None = None,
    sfem_verify_dwell_s: float = SFEM_VERIFY_DWELL_S,
) -> Profile:
    """The profile ending with program and verify (design 4): a program step, then a verification
    step that heats the plate again by heat_c (lamp on) at `position` (default: where the profile
    ends, so no turn is needed) while the boards send compensated output.

    An SFEM profile's verification is a cool-down instead (station/daemon/sfem_program.py): the
    cubic SFEM holds only over the temperatures its steps spanned (a board clamps to them), so the
    plate goes back through that range, not above it: the chamber back to the profile's coldest set
    point (the lamp off without a chamber) for `sfem_verify_dwell_s` of sample time."""
    pos = profile.steps[-1].position if position is None else _pos(position)
    if profile.analysis == "sfem":
        set_points = [s.chamber_setpoint_c for s in profile.steps if s.chamber_setpoint_c is not None]
        verify = Step("verify cool-down", pos, lamp=False, chamber_setpoint_c=min(set_points) if set_points else None,
                      require="none", settle_s=settle_s, dwell_s=sfem_verify_dwell_s,
                      timeout_s=max(timeout_s, 2.0 * (settle_s + sfem_verify_dwell_s)))
        what = f"verify (the plate cools back through the SFEM's range for {sfem_verify_dwell_s:g} s, compensated " \
               "output against the station's model)"
    else:
        verify = Step("verify hot", pos, lamp=True, require="heat", heat_c=heat_c, settle_s=settle_s, timeout_s=timeout_s)
        what = f"verify (lamp heats +{heat_c:g} C, compensated drift E judged)"
    steps = profile.steps + (Step("program", pos, lamp=False, require="program", timeout_s=600.0), verify)
    return Profile(
        name or f"{profile.name}-verified",
        steps,
        description=f"{profile.description}; then program (write, read back, compensation on) and {what}",
        analysis=profile.analysis,
        builtin=profile.builtin,
        verify=criteria or VerifyCriteria(),
        sfem_reference_temp_c=profile.sfem_reference_temp_c,
        sfem_ref_sigma_deg=profile.sfem_ref_sigma_deg,
        board_selfcal=profile.board_selfcal,
    )


BUILTIN_PROFILES: dict[str, Profile] = {
    p.name: p for p in (_fast_thermal(), _six_position(), _sfem24(), _validation(),
                        with_program_verify(_fast_thermal(), name="fast-thermal-verified"))
}


def profile_from_config(name: str, cfg) -> Profile:
    """A site profile from its validated config model (station.config.ProfileConfig)."""
    steps = tuple(
        Step(
            name=s.name,
            position=_pos(s.position),
            lamp=s.lamp,
            chamber_setpoint_c=s.chamber_setpoint_c,
            require=s.require,
            dwell_s=s.dwell_s,
            settle_s=s.settle_s,
            timeout_s=s.timeout_s,
        )
        for s in cfg.steps
    )
    prof = Profile(name, steps, description=cfg.description, analysis=cfg.analysis, builtin=False,
                   sfem_reference_temp_c=getattr(cfg, "sfem_reference_temp_c", None),
                   sfem_ref_sigma_deg=getattr(cfg, "sfem_ref_sigma_deg", None),
                   board_selfcal=bool(getattr(cfg, "board_selfcal", False)))
    pv = getattr(cfg, "program_verify", None)
    if pv is not None:
        prof = with_program_verify(
            prof, name=name, position=pv.position, heat_c=pv.heat_c, settle_s=pv.settle_s, timeout_s=pv.timeout_s,
            criteria=VerifyCriteria(e_ratio_max=pv.e_ratio_max, e_floor_mg=pv.e_floor_mg,
                                    full_range_c=pv.full_range_c, curvature_limit_mg=pv.curvature_limit_mg),
            sfem_verify_dwell_s=float(getattr(pv, "sfem_verify_dwell_s", SFEM_VERIFY_DWELL_S)),
        )
    return prof


def all_profiles(config=None) -> dict[str, Profile]:
    out = dict(BUILTIN_PROFILES)
    if config is not None:
        for name, prof in config.profiles.items():
            out[name] = profile_from_config(name, prof)
    return out


def check_profile_name(name: str, config=None) -> None:
    """A command line's profile that does not exist: one line (StationError) naming the known
    ones, before any hardware is opened (a newcomer's typo must not end in a traceback)."""
    from contracts.types import StationError

    known = all_profiles(config)
    if name not in known:
        raise StationError(f"unknown profile {name!r} (known: {', '.join(known)})")
