"""Station configuration: one TOML file, validated with pydantic.

A bad file gives one StationError line naming the key and what is wrong, e.g.
`config station.toml: slots[2].serial: slot 's03' needs exactly one of 'serial' or 'can'`.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from contracts.positions import POSITION_INDEX, POSITION_NAMES
from station.decisions.limits import ProductSpec, product_for, resolve_products
from station.steps import kind_names
from contracts.types import StationError


class _Model(BaseModel):
    # NaN/inf are refused everywhere: a NaN limit compares False and would blind a safety check.
    model_config = ConfigDict(extra="forbid", frozen=False, allow_inf_nan=False)


class CanNode(_Model):
    """A CAN board: node id on a bus given by python-can interface and channel."""

    interface: str = "slcan"
    channel: str
    node: int = Field(ge=1, le=127)
    bitrate: int = 500_000


class SlotConfig(_Model):
    """One DUT place on the plate: a serial port / pyserial URL or a CAN node, never both."""

    name: str = Field(min_length=1, max_length=32)
    serial: str | None = None
    can: CanNode | None = None

    @model_validator(mode="after")
    def _one_link(self) -> "SlotConfig":
        if (self.serial is None) == (self.can is None):
            raise ValueError(f"slot {self.name!r} needs exactly one of 'serial' or 'can'")
        return self

    @property
    def link(self) -> str:
        if self.serial is not None:
            return f"serial {self.serial}"
        assert self.can is not None
        return f"can {self.can.interface}:{self.can.channel} node {self.can.node}"


class ModbusTcp(_Model):
    host: str
    port: int = Field(default=502, ge=1, le=65535)


class ModbusRtu(_Model):
    port: str
    baudrate: int = 19200


class ModbusDevice(_Model):
    """A Modbus device (design 3.3): Modbus TCP (host/port) or RTU (serial port), and a unit id."""

    tcp: ModbusTcp | None = None
    rtu: ModbusRtu | None = None
    unit: int = Field(ge=0, le=247)
    timeout_s: float = Field(default=1.0, gt=0)

    @model_validator(mode="after")
    def _one_link(self) -> "ModbusDevice":
        if (self.tcp is None) == (self.rtu is None):
            raise ValueError("needs exactly one of 'tcp' or 'rtu'")
        return self

    @property
    def link_key(self) -> tuple:
        if self.tcp is not None:
            return ("tcp", self.tcp.host, self.tcp.port)
        assert self.rtu is not None
        return ("rtu", self.rtu.port, self.rtu.baudrate)

    @property
    def link(self) -> str:
        if self.tcp is not None:
            return f"modbus tcp {self.tcp.host}:{self.tcp.port} unit {self.unit}"
        assert self.rtu is not None
        return f"modbus rtu {self.rtu.port} unit {self.unit}"


class Limits(_Model):
    """Safety limits (design 3.3). The lamp on-time is counted in the plant's time (see safety.py)."""

    max_dut_temp_c: float = 85.0
    max_plate_temp_c: float = 90.0
    lamp_max_on_s: float = Field(default=3600.0, gt=0)
    relay_watchdog_s: float = Field(default=10.0, ge=0, le=3600,
                                    description="lamp relay host watchdog (design 3.3), wall s; 0 = not used")


class Timing(_Model):
    """Wall-clock supervision of the links (not the science, which runs on sample time)."""

    speed: float = Field(default=1.0, gt=0, description="plant time per wall second: 1 on real hardware")
    stall_timeout_s: float = Field(default=10.0, gt=0, description="wall seconds the station listened without a sample -> slot faulted "
                                   "(not while the program step has the streams stopped; a held-up loop counts as one read)")
    identify_timeout_s: float = Field(default=3.0, gt=0)
    fixture_timeout_s: float = Field(default=120.0, gt=0, description="wall seconds for a fixture move")
    read_period_s: float = Field(default=0.1, gt=0, le=5, description="wall seconds between block reads of a link, at least (design 2.2, read pace)")
    reads_per_s: float = Field(default=250.0, gt=0, description="block reads a second of all links together beyond which "
                               "links whose reads are small are read less often (design 2.2, read pace): a read costs the "
                               "event loop the same whatever it carries")
    intake_cost_us_per_sample: float = Field(
        default=8.0, gt=0, le=10_000,
        description="the station's CPU microseconds per sample until it has measured its own (while boards "
                    "stream): a batch whose boards demand more samples/s than this PC follows is refused at its "
                    "start (docs/design.md, capacity; station/daemon/intake_monitor.py)")
    plate_again_after_s: float = Field(default=40.0, gt=0, description="SAMPLE seconds after the operator's Done "
                                       "before a plate that the DUTs do not measure at the asked position is asked "
                                       "for again, with what they face (a wrong turn is asked for at once)")


class Token(_Model):
    token: str = Field(min_length=8)
    role: Literal["operator", "mes", "admin"]
    name: str = ""


class RouteCheck(_Model):
    """The MES's pre-test route check ([mes.route_check], design 5.4): "may this serial be tested at
    this operation now?", asked per DUT once its identity and label are known and before the lamp
    heats. A "no" stops that slot with the MES's reason; `when_unanswered` is the site's policy when
    the MES gives no usable answer (down, slow, an error, an answer it cannot read)."""

    url: str = Field(min_length=1, max_length=2048, description="the MES's route check; may hold {serial}, "
                     "{label_serial}, {operation}, {station}, {slot}, {work_order}, {part_number}, {lot} "
                     "(URL-quoted)")
    method: Literal["GET", "POST"] = Field(default="GET", description="POST sends the same fields as a JSON body")
    timeout_s: float = Field(default=5.0, gt=0, le=120, description="one call's timeout, wall s (the whole answer)")
    operation: str = Field(default="thermal-calibration", min_length=1, max_length=64,
                           description="this station's operation as the MES routes it")
    headers: dict[str, str] = Field(default_factory=dict, description="sent with every call (e.g. Authorization)")
    allowed_field: str = Field(default="allowed", min_length=1, max_length=128,
                               description="dotted path of the JSON answer's yes/no: true or yes/ok/allowed/pass "
                               "= may be tested; false or no/hold/refused/blocked = a no")
    reason_field: str = Field(default="reason", min_length=1, max_length=128,
                              description="dotted path of the MES's reason in words")
    refuse_statuses: list[int] = Field(default_factory=lambda: [403, 409, 423],
                                       description="HTTP statuses that are a no whatever the body says")
    when_unanswered: Literal["refuse", "proceed_and_flag"] = Field(
        default="refuse", description="no usable answer: 'refuse' stops the slot (the part is not tested); "
        "'proceed_and_flag' tests it and flags its record and its MES message as not route-checked")

    @field_validator("refuse_statuses")
    @classmethod
    def _statuses(cls, v: list[int]) -> list[int]:
        bad = [s for s in v if not 300 <= s <= 599 or s in (408, 429)]
        if bad:
            raise ValueError(f"{bad}: a refusal is a 3xx-5xx status other than 408/429 (those mean 'ask again')")
        return v


class Mes(_Model):
    """The MES webhook ([mes]): where each final verdict is posted (through the durable outbox, once
    per record) and how a refused or unreachable MES is retried; and its route check, if any."""

    webhook_url: str | None = None
    timeout_s: float = Field(default=10.0, gt=0, le=600, description="one POST's timeout")
    base_delay_s: float = Field(default=2.0, gt=0, le=3600, description="first retry after this; doubles each time")
    max_delay_s: float = Field(default=600.0, gt=0, le=86_400, description="retries never wait longer")
    poll_s: float = Field(default=2.0, gt=0, le=600, description="how often the outbox looks for due messages")
    batch: int = Field(default=20, ge=1, le=1000, description="messages sent per look")
    route_check: RouteCheck | None = Field(default=None, description="ask the MES before testing each part "
                                           "(None: no route check)")


class Http(_Model):
    host: str = "127.0.0.1"
    port: int = Field(default=8080, ge=0, le=65535)
    max_body_bytes: int = Field(default=1 << 20, ge=1024, le=1 << 30,
                                description="larger request bodies are answered 413 before they are read")
    max_event_streams: int = Field(default=32, ge=1, le=10_000,
                                   description="open /api/events streams; more are answered 503")
    header_timeout_s: float = Field(default=10.0, gt=0, le=600,
                                    description="a connection's request head must be complete this soon, else closed")
    keep_alive_s: float = Field(default=5.0, gt=0, le=600, description="an idle keep-alive connection is closed after")
    max_connections: int = Field(default=512, ge=8, le=100_000,
                                 description="open HTTP connections; beyond, the oldest waiting for a head is evicted")


class Metrics(_Model):
    """GET /metrics (Prometheus, docs/metrics.md): who may scrape it without a token. A scraper
    whose peer address (the TCP connection's, never X-Forwarded-For) is in `allow` needs none,
    unless its request carries a forwarding header (a proxy); anyone else needs a token of role
    admin or mes. [] = a token for everyone."""

    allow: list[str] = Field(default=["127.0.0.1/32", "::1/128"], max_length=256,
                             description="CIDR networks that may scrape /metrics without a token")

    @field_validator("allow")
    @classmethod
    def _cidrs(cls, v: list[str]) -> list[str]:
        import ipaddress

        for net in v:
            try:
                ipaddress.ip_network(net, strict=True)
            except ValueError as exc:
                raise ValueError(f"not a CIDR network: {net!r} ({exc})") from None
        return v


class StepConfig(_Model):
    """One profile step (see station/profiles.py for the meaning; its kind's own rules are checked
    when the profile is built: parse_config)."""

    name: str
    position: int | str
    lamp: bool = False
    chamber_setpoint_c: float | None = None
    require: str = Field(default="segment", description="the step's kind (station/steps), one a site profile may name")
    dwell_s: float = Field(default=0.0, ge=0, description="sample seconds to log for 'static'/'none'")
    settle_s: float = Field(default=0.0, ge=0, description="sample seconds ignored after the move")
    timeout_s: float = Field(gt=0, description="in sample time")

    @field_validator("require")
    @classmethod
    def _known_kind(cls, v: str) -> str:
        allowed = kind_names(configurable=True)
        if v in allowed:
            return v
        if v in kind_names():
            raise ValueError(f"step kind {v!r} cannot be named in a profile's steps (they take: {', '.join(allowed)}; "
                             "program and verify come from [profiles.NAME.program_verify])")
        raise ValueError(f"unknown step kind {v!r} (known: {', '.join(allowed)})")

    @field_validator("position")
    @classmethod
    def _known_position(cls, v: int | str) -> int | str:
        if isinstance(v, str):
            if v not in POSITION_INDEX:
                raise ValueError(f"unknown position {v!r} (known: P, N, +x..-z, sfem-z0..sfem-x315)")
        elif not 0 <= v < len(POSITION_NAMES):
            raise ValueError(f"position index {v} out of range 0..{len(POSITION_NAMES) - 1}")
        return v


class ProgramVerifyConfig(_Model):
    """`[profiles.NAME.program_verify]`: end the profile with program and verify (design 4)."""

    position: int | str | None = None  # default: where the profile's last step is
    heat_c: float = Field(default=15.0, ge=15.0, description="rise of every DUT's temperature, C")
    settle_s: float = Field(default=20.0, ge=0)
    timeout_s: float = Field(default=2400.0, gt=0)
    e_ratio_max: float = Field(default=0.25, gt=0, le=1)
    e_floor_mg: float = Field(default=2.0, ge=0)
    full_range_c: float = Field(default=70.0, gt=0)
    curvature_limit_mg: float = Field(default=4.0, ge=0)
    # an SFEM profile's verification is a cool-down back through the SFEM's range (station/profiles.py
    # with_program_verify): how long, in sample seconds
    sfem_verify_dwell_s: float = Field(default=1800.0, gt=0, description="SFEM profiles: the verification "
                                       "cool-down's length, sample seconds")


class ProfileConfig(_Model):
    description: str = ""
    analysis: Literal["thermal", "sfem", "none"] = "none"
    steps: list[StepConfig] = Field(min_length=1)
    program_verify: ProgramVerifyConfig | None = None
    # SFEM only (station/profiles.py Profile): the verdict's reference temperature (default 25 C) and
    # the fixture's direction error where a step cannot measure it (default: station/science/sfem.py)
    sfem_reference_temp_c: float | None = Field(default=None, ge=-60.0, le=150.0)
    sfem_ref_sigma_deg: float | None = Field(default=None, gt=0.0, le=20.0)
    # thermal profiles: the boards' own calibrators as a second opinion (station/profiles.py, docs/profiles.md)
    board_selfcal: bool = Field(default=False, description="boards with caps 'scal': their own calibrator on during "
                                "the thermal steps, its TDB/TDSF compared with the station's (check "
                                "board_selfcal_agrees)")


class CertificateConfig(_Model):
    """`[certificate]`: who issues the station's calibration certificates (station/records/certificate.py,
    ISO/IEC 17025:2017 7.8.2.1). Stored with every batch (the config snapshot), so a certificate
    reprinted later names the issuer of its run. A key left empty prints "not configured": the
    station never makes up an organisation or a signatory."""

    issuer: str = Field(default="", max_length=200, description="organisation (laboratory) issuing the certificates")
    address: str = Field(default="", max_length=300, description="its address / the place the calibrations are done")
    authorised_by: str = Field(default="", max_length=200,
                               description="name and function of the person authorising the certificates")
    reference_thermometer: str = Field(default="", max_length=300,
                                       description="the plate reference thermometer's own calibration (certificate "
                                                   "no., due date), quoted in the traceability statement")


class Cfx(_Model):
    """IPC-CFX (IPC-2591) over AMQP 1.0 ([cfx], docs/cfx.md): the station tells the line its work,
    tests and state in CFX messages, through a durable outbox (nothing lost while the broker is down,
    each message once, in order)."""

    enabled: bool = False
    broker_url: str = Field(default="amqp://guest:guest@127.0.0.1:5672", min_length=1, max_length=2048,
                            description="the AMQP 1.0 broker: amqp[s]://user:password@host:port")
    address: str = Field(default="/exchange/amq.topic", min_length=1, max_length=512,
                         description="AMQP target the messages are sent to (RabbitMQ: /exchange/NAME routes by "
                                     "the subject; /queue/NAME a durable queue)")
    handle: str = Field(default="", max_length=256, description="the station's CFX handle (envelope Source), e.g. "
                        "//Company/Line1/ThermalCal1; '' = //thermal-cal-station/<name>")
    subject: Literal["message_name", "handle.message_name"] = Field(
        default="message_name", description="the AMQP subject (a topic exchange's routing key): the MessageName, "
        "or the CFX SDK's default <handle>.<MessageName>")
    timeout_s: float = Field(default=10.0, gt=0, le=600, description="connect / one message's settlement")
    base_delay_s: float = Field(default=1.0, gt=0, le=3600, description="first retry after this; doubles each time")
    max_delay_s: float = Field(default=120.0, gt=0, le=86_400, description="retries never wait longer")
    poll_s: float = Field(default=2.0, gt=0, le=600, description="how often the outbox looks for new data")
    lookback_h: float = Field(default=24.0, gt=0, le=24 * 366,
                              description="batches created this long before the worker starts are still announced")
    complete_after_s: float = Field(default=60.0, ge=0, le=86_400,
                                    description="an ended batch with unjudged runs is completed after this long")


def _hostname() -> str:
    import socket

    return (socket.gethostname() or "station")[:64]


class StationConfig(_Model):
    # the station's name, stamped on every batch, run, result and audit row: stations that share
    # one database (PostgreSQL) are told apart by it, so the default is the host's name
    name: str = Field(default_factory=_hostname, min_length=1, max_length=64)
    database_url: str = "sqlite:///var/station.db"
    # the station's journal (db/journal.py): events the database has not taken yet, durable on this
    # station, forwarded when the database answers. Default: beside a SQLite file (<file>.journal);
    # for PostgreSQL, ~/.local/state/station/<name>-<host>-<port>-<database>.journal
    journal_path: str | None = Field(default=None, min_length=1, max_length=1024)
    mes_webhook_url: str | None = None  # the webhook's URL alone (older configs); [mes] webhook_url is the same
    mes: Mes = Mes()
    http: Http = Http()
    metrics: Metrics = Metrics()
    cfx: Cfx = Cfx()  # IPC-CFX over AMQP 1.0 (docs/cfx.md)
    limits: Limits = Limits()
    timing: Timing = Timing()
    slots: list[SlotConfig] = Field(min_length=1)
    lamp: ModbusDevice
    fixture: ModbusDevice | None = None
    thermometer: ModbusDevice | None = None
    chamber: ModbusDevice | None = None
    tokens: list[Token] = []
    profiles: dict[str, ProfileConfig] = {}
    # Spec limits per product (station/decisions/limits.py): built-ins for LIS3DSH and ADXL355, which a
    # site's [products.NAME] with the same key replaces.
    products: dict[str, ProductSpec] = {}
    # set by `station replay` (station/replay): every batch of this daemon re-runs recorded data
    # from this source; such batches are stored as replays and never sent to the MES
    replay_of: str | None = Field(default=None, max_length=256)
    # who issues the calibration certificates (optional; printed as "not configured" when empty)
    certificate: CertificateConfig = CertificateConfig()
    # where the station's lock files of its ports, CAN channels and Modbus endpoints live (station/daemon/
    # ownership.py: one station owns its hardware); default per user: $XDG_RUNTIME_DIR/accel-station or
    # /tmp/accel-station-locks-<uid>. The SQLite database's lock file always sits next to the database.
    lock_dir: str | None = Field(default=None, min_length=1, max_length=1024)

    @model_validator(mode="after")
    def _one_webhook(self) -> "StationConfig":
        """`mes_webhook_url` and `[mes] webhook_url` name one webhook: either sets it, both must agree."""
        if self.mes_webhook_url and self.mes.webhook_url and self.mes_webhook_url != self.mes.webhook_url:
            raise ValueError("mes_webhook_url and [mes] webhook_url differ: set one")
        url = self.mes.webhook_url or self.mes_webhook_url
        self.mes = self.mes.model_copy(update={"webhook_url": url})
        self.mes_webhook_url = url
        return self

    @model_validator(mode="after")
    def _unique(self) -> "StationConfig":
        seen: set[str] = set()
        links: set[tuple] = set()
        for s in self.slots:
            if s.name in seen:
                raise ValueError(f"duplicate slot name {s.name!r}")
            seen.add(s.name)
            key = ("serial", s.serial) if s.serial else ("can", s.can.interface, s.can.channel, s.can.node)  # type: ignore[union-attr]
            if key in links:
                raise ValueError(f"slot {s.name!r} uses the same link as another slot ({s.link})")
            links.add(key)
        toks = [t.token for t in self.tokens]
        if len(toks) != len(set(toks)):
            raise ValueError("duplicate auth token")
        return self

    def slot(self, name: str) -> SlotConfig:
        for s in self.slots:
            if s.name == name:
                return s
        raise KeyError(name)

    def role_of(self, token: str) -> str | None:
        for t in self.tokens:
            if t.token == token:
                return t.role
        return None

    def product_specs(self) -> dict[str, ProductSpec]:
        """Built-in products overlaid with the site's (station/decisions/limits.py)."""
        return resolve_products(self.products)

    def product_for(self, sensor: str | None, part_number: str | None = None) -> ProductSpec | None:
        return product_for(self.product_specs(), sensor, part_number)

    def snapshot(self) -> dict:
        """The config as stored with each batch; auth tokens are masked."""
        data = self.model_dump(mode="json")
        # every limits set in force (built-ins included), so a stored verdict can be traced to it
        data["products"] = {k: v.model_dump(mode="json") for k, v in self.product_specs().items()}
        data["tokens"] = [{"role": t["role"], "name": t["name"], "token": "***"} for t in data["tokens"]]
        if isinstance(data.get("cfx"), dict):  # the broker's password is no part of a batch's record
            import re

            data["cfx"]["broker_url"] = re.sub(r"//[^/@]*@", "//***@", str(data["cfx"]["broker_url"]))
        return data


def _loc(loc: tuple) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        elif part in ("function-after", "model-after") or "[" in str(part):
            continue
        else:
            out += ("." if out else "") + str(part)
    return out or "(top level)"


def format_validation_error(exc: ValidationError, source: str) -> str:
    err = exc.errors()[0]
    where = _loc(tuple(p for p in err["loc"] if not (isinstance(p, str) and p.startswith("function-"))))
    msg = err["msg"]
    if msg.startswith("Value error, "):
        msg = msg[len("Value error, "):]
    if err["type"] == "extra_forbidden":
        msg = "unknown key"
    elif err["type"] == "missing":
        msg = "required key is missing"
    more = len(exc.errors()) - 1
    tail = f" (and {more} more problem{'s' if more > 1 else ''})" if more else ""
    return f"config {source}: {where}: {msg}{tail}"


def parse_config(data: dict, source: str = "<dict>") -> StationConfig:
    try:
        cfg = StationConfig.model_validate(data)
    except ValidationError as exc:
        raise StationError(format_validation_error(exc, source)) from None
    # Site profiles are checked here too, so a bad step is a config error, not a batch failure.
    from station.profiles import profile_from_config

    for name, prof in cfg.profiles.items():
        try:
            profile_from_config(name, prof)
        except ValueError as exc:
            raise StationError(f"config {source}: profiles.{name}: {exc}") from None
    return cfg


def load_config(path: str | Path) -> StationConfig:
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise StationError(f"config file not found: {p}") from None
    except OSError as exc:
        raise StationError(f"cannot read config {p}: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        line = exc.object[: exc.start].count(b"\n") + 1
        raise StationError(f"config {p}: line {line}: not UTF-8 text (byte 0x{exc.object[exc.start]:02x})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise StationError(f"config {p}: TOML syntax error: {exc}") from None
    return parse_config(data, str(p))
