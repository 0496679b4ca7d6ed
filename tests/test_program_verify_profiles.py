"""Program and verify as profile data: the built-in fast-thermal-verified, any site profile ending
with it from config, and the rules a verification step must follow."""

import tomllib

import pytest

from station.config import parse_config
from station.profiles import BUILTIN_PROFILES, Profile, Step, all_profiles, with_program_verify
from tests.test_config import MIN


def test_fast_thermal_verified_is_fast_thermal_plus_program_and_verify():
    ft, fv = BUILTIN_PROFILES["fast-thermal"], BUILTIN_PROFILES["fast-thermal-verified"]
    assert fv.steps[:4] == ft.steps
    prog, heat = fv.steps[4], fv.steps[5]
    assert prog.require == "program" and not prog.lamp and fv.program_step == 4
    assert heat.require == "heat" and heat.lamp and heat.heat_c >= 15.0
    assert prog.position == heat.position == ft.steps[-1].position  # no turn: N, where fast-thermal ends
    assert fv.verify.e_ratio_max == 0.25 and fv.verify.e_floor_mg == 2.0
    j = fv.to_json()
    assert j["program_verify"] is True and j["steps"][5]["heat_c"] == heat.heat_c
    assert ft.program_step is None and ft.to_json()["program_verify"] is False


def test_site_profile_ends_with_program_and_verify_from_config():
    text = MIN + """
[profiles.my-thermal]
analysis = "thermal"
steps = [
  { name = "P cold", position = "P", require = "segment", timeout_s = 1800 },
  { name = "P hot", position = "P", lamp = true, require = "segment", timeout_s = 3000 },
  { name = "N hot", position = "N", lamp = true, require = "segment", timeout_s = 3000 },
  { name = "N cold", position = "N", require = "segment", timeout_s = 3000 },
]
[profiles.my-thermal.program_verify]
position = "P"
heat_c = 18
e_ratio_max = 0.2
"""
    cfg = parse_config(tomllib.loads(text), "<t>")
    p = all_profiles(cfg)["my-thermal"]
    assert [s.require for s in p.steps[-2:]] == ["program", "heat"]
    assert p.steps[-1].heat_c == 18 and p.steps[-1].position_name == "P"
    assert p.verify.e_ratio_max == 0.2


def test_verification_rules():
    base = BUILTIN_PROFILES["fast-thermal"]
    with pytest.raises(ValueError, match="at least 15 C"):
        with_program_verify(base, heat_c=10.0)
    with pytest.raises(ValueError, match="must follow a program step"):
        Profile("x", (Step("h", 0, lamp=True, require="heat", heat_c=20),), analysis="thermal")
    with pytest.raises(ValueError, match="needs analysis='thermal'"):
        with_program_verify(BUILTIN_PROFILES["validation"])
    with pytest.raises(ValueError, match="lamp on or a chamber"):
        Profile("x", (Step("p", 0, require="program"), Step("h", 0, require="heat", heat_c=20)), analysis="thermal")
