"""Station config: the example parses; every mistake is one StationError line naming the key."""

from pathlib import Path

import pytest

from station.config import load_config, parse_config
from station.profiles import BUILTIN_PROFILES, all_profiles
from contracts.types import StationError

ROOT = Path(__file__).resolve().parents[1]

MIN = """
[[slots]]
name = "s01"
serial = "/dev/ttyACM0"
[lamp]
tcp = { host = "127.0.0.1", port = 5020 }
unit = 1
"""


def _load(tmp_path, text: str):
    p = tmp_path / "station.toml"
    p.write_text(text)
    return load_config(p)


def _err(tmp_path, text: str) -> str:
    with pytest.raises(StationError) as ei:
        _load(tmp_path, text)
    msg = str(ei.value)
    assert "\n" not in msg
    return msg


def test_example_config_parses():
    cfg = load_config(ROOT / "station.example.toml")
    assert [s.name for s in cfg.slots] == ["s01", "s02", "c01", "c02"]
    assert cfg.slots[2].can.node == 1 and cfg.slots[2].can.interface == "socketcan"
    assert cfg.lamp.tcp.port == 502 and cfg.lamp.unit == 1
    assert cfg.thermometer.rtu.port == "/dev/ttyUSB0"
    assert cfg.chamber is None
    assert cfg.role_of("change-me-mes-token-0001") == "mes"
    assert cfg.role_of("nope") is None
    profs = all_profiles(cfg)
    assert set(BUILTIN_PROFILES) <= set(profs)
    assert [s.name for s in profs["quick-thermal"].steps] == ["P ambient", "P hot", "N hot", "N ambient"]
    assert profs["quick-thermal"].steps[2].position == 1
    snap = cfg.snapshot()
    assert all(t["token"] == "***" for t in snap["tokens"])


def test_minimal_config_defaults(tmp_path):
    cfg = _load(tmp_path, MIN)
    assert cfg.http.port == 8080 and cfg.limits.max_dut_temp_c == 85.0 and cfg.timing.speed == 1.0
    assert cfg.fixture is None


def test_builtin_profiles_are_data():
    ft = BUILTIN_PROFILES["fast-thermal"]
    assert [(s.position_name, s.lamp) for s in ft.steps] == [("P", False), ("P", True), ("N", True), ("N", False)]
    assert ft.analysis == "thermal"
    assert len(BUILTIN_PROFILES["sfem-24"].steps) == 24 * 3
    assert set(BUILTIN_PROFILES) == {"fast-thermal", "six-position", "sfem-24", "validation", "fast-thermal-verified"}


@pytest.mark.parametrize(
    "text, expect",
    [
        (MIN.replace('serial = "/dev/ttyACM0"', ""), "slots[0]: slot 's01' needs exactly one of 'serial' or 'can'"),
        (MIN + "\n[limits]\nmax_dut_temp = 80\n", "limits.max_dut_temp: unknown key"),
        (MIN.replace("unit = 1", "unit = 300"), "lamp.unit: Input should be less than or equal to 247"),
        (MIN.replace("[lamp]\ntcp = { host = \"127.0.0.1\", port = 5020 }\nunit = 1\n", ""), "lamp: required key is missing"),
        (MIN + '\n[[slots]]\nname = "s01"\nserial = "/dev/ttyACM1"\n', "duplicate slot name 's01'"),
        (MIN + '\n[[slots]]\nname = "c1"\ncan = { channel = "can0", node = 200 }\n', "slots[1].can.node"),
        (MIN + '\n[timing]\nspeed = -1\n', "timing.speed: Input should be greater than 0"),
        (MIN + '\n[[tokens]]\ntoken = "abcdefgh1"\nrole = "boss"\n', "tokens[0].role"),
        (
            MIN + '\n[profiles.x]\n[[profiles.x.steps]]\nname = "a"\nposition = "Q"\ntimeout_s = 10\n',
            "profiles.x.steps[0].position: unknown position 'Q'",
        ),
        (
            MIN + '\n[profiles.x]\n[[profiles.x.steps]]\nname = "a"\nposition = "P"\nrequire = "static"\ntimeout_s = 10\n',
            "profiles.x: steps[0]: require='static' needs dwell_s > 0",
        ),
        (MIN + "\n[http\nport = 1\n", "TOML syntax error"),
    ],
)
def test_bad_config_names_key(tmp_path, text, expect):
    msg = _err(tmp_path, text)
    assert expect in msg, msg
    assert "station.toml" in msg


def test_missing_file_is_clear(tmp_path):
    with pytest.raises(StationError, match="config file not found"):
        load_config(tmp_path / "nope.toml")


def test_parse_dict_and_site_profile_overrides_builtin():
    data = {
        "slots": [{"name": "a", "serial": "loop://"}],
        "lamp": {"tcp": {"host": "127.0.0.1"}, "unit": 1},
        "profiles": {"fast-thermal": {"analysis": "thermal", "steps": [
            {"name": "only", "position": 0, "require": "none", "dwell_s": 5, "timeout_s": 10}]}},
    }
    cfg = parse_config(data)
    assert len(all_profiles(cfg)["fast-thermal"].steps) == 1


def test_example_config_product_is_the_one_used_for_lis3dsh():
    cfg = load_config(ROOT / "station.example.toml")
    spec = cfg.product_for("LIS3DSH")
    assert (spec.name, spec.version) == ("LIS3DSH-line", "1")
    assert [g.name for g in spec.grades] == ["A", "B"]


def test_the_mes_webhook_and_its_retries_are_set_in_toml(tmp_path):
    """[mes] sets the webhook and how a refused or unreachable MES is retried; the older top-level
    mes_webhook_url still names the same webhook; two different URLs are refused."""
    from web.mes_outbox import OutboxConfig

    cfg = _load(tmp_path, 'name = "line-3"\n' + MIN + """
[mes]
webhook_url = "http://127.0.0.1:9/hook"
timeout_s = 3
base_delay_s = 0.5
max_delay_s = 30
poll_s = 1
batch = 5
""")
    out = OutboxConfig.from_config(cfg)
    assert out == OutboxConfig(url="http://127.0.0.1:9/hook", timeout_s=3.0, base_delay_s=0.5, max_delay_s=30.0,
                               poll_s=1.0, batch=5, station_name="line-3")
    legacy = _load(tmp_path, 'mes_webhook_url = "http://127.0.0.1:9/old"\n' + MIN)
    assert OutboxConfig.from_config(legacy).url == "http://127.0.0.1:9/old"
    assert OutboxConfig.from_config(legacy).base_delay_s == 2.0  # the documented default
    assert OutboxConfig.from_config(_load(tmp_path, MIN)) is None
    assert "mes_webhook_url and [mes] webhook_url differ" in _err(
        tmp_path, 'mes_webhook_url = "http://a/1"\n' + MIN + '[mes]\nwebhook_url = "http://b/2"\n')
    assert "mes.base_delay_s" in _err(tmp_path, MIN + "[mes]\nbase_delay_s = -1\n")
