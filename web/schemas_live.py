"""Response models of what the daemon holds live: a batch's status (GET /api/batches/{id}), its
slots, steps, time left and operator prompt, and the slots of the station (GET /api/slots).

Producers: station/daemon/batch_view.py `status`, station/daemon/progress.py `batch_extras`,
station/daemon/dut_run.py `DutRun.status`, station/daemon/slots.py, web/views.py (batch_view,
slot_view, prompt_view); a batch the daemon no longer holds comes from web/db_repo.py `batch`.
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import ConfigDict, Field

from station.steps import kind_names, row_kinds
from web.schemas_common import (
    CodedWords, DecisionFields, DecisionOut, ProgramVerifyOut, TraceFields, _Out, free_form, one_of,
)
from web.schemas_thermal import CalibrationResultJson
from web.schemas_program import LiveProgram, LiveVerificationJson


class LinkStats(_Out):
    """Counters of one board link (drivers/base.py LinkStats)."""

    frames_ok: int = Field(default=0, description="frames received and parsed")
    frames_bad_checksum: int = Field(default=0, description="frames dropped for a bad checksum")
    frames_malformed: int = Field(default=0, description="short line, unknown type, unparsable field")
    bytes_skipped: int = Field(default=0, description="garbage bytes skipped between frames")
    samples_lost: int = Field(default=0, description="samples missing by sequence gaps or dropped from a full queue")
    samples_lost_queue: int = Field(default=0, description="of samples_lost: dropped from the driver's full queue")
    samples_lost_station: int = Field(default=0, description="of samples_lost: lost while the station ran behind "
                                      "this link (its own backlog, not the part's; queue drops included)")
    errors_reported: int = Field(default=0, description="error frames the board sent")
    resets: int = Field(default=0, description="times the board restarted while streaming (its run ended there)")
    clock_jumps: int = Field(default=0, description="times its clock jumped while its seq ran on (its run ended there)")
    frames_after_break: int = Field(default=0, description="sample frames of another timeline after a reset or clock jump, not taken")
    board_restarts: int = Field(default=0, description="times the board restarted between two identity replies "
                                "(its reported boots count moved: watchdog, fault, pin or software reset)")
    sensor_reinits_reported: int = Field(default=0, description="of errors_reported: E,SENSOR frames (the board "
                                         "found its sensor silent and re-initialised it)")


class Overload(_Out):
    """Is the station keeping up with its boards? (station/daemon/intake_monitor.py)"""

    behind_s: float = Field(description="the most the station runs behind any board link, wall seconds")
    alarm: str | None = Field(default=None, description="in words while the station cannot follow its boards "
                              "(behind by 3 s or more, or samples lost to its backlog in the last 30 s); null when it can")
    lost_station: int = Field(default=0, description="samples lost to the station's own backlog in this batch")
    lost_by_slot: dict[str, int] = Field(default_factory=dict, description="slot -> samples lost to the station's "
                                         "backlog (slots without loss left out)")
    cost_us_per_sample: float | None = Field(default=None, description="the station's CPU microseconds per sample "
                                             "(measured while boards stream, else the configured figure)")
    capacity_samples_per_s: float | None = Field(default=None, description="samples per second this PC follows")
    intake_samples_per_s: float | None = Field(default=None, description="samples per second taken in lately")
    cpu_share: float | None = Field(default=None, description="the station process's CPU seconds per wall second "
                                    "lately (0.85 or more: saturated, a gap on a link then is the station's loss)")


class StepInfo(_Out):
    """The batch's current profile step (station/profiles.py Step.to_json + index and count)."""

    index: int | None = Field(default=None, description="index of the step in the profile (-1 before the first)")
    name: str | None = Field(default=None, description="the step's name")
    count: int | None = Field(default=None, description="number of steps of the profile")
    position: int | None = Field(default=None, description="plate position index (contracts/positions.py)")
    position_name: str | None = Field(default=None, description="plate position name, e.g. P, N, +z")
    lamp: bool | None = Field(default=None, description="the lamp is on during the step")
    chamber_setpoint_c: float | None = Field(default=None, description="chamber set point, C (null: no chamber)")
    require: str | None = one_of(kind_names(), "the step's kind: what every DUT must log before the step ends "
                                 "(station/steps)", default=None)
    dwell_s: float | None = Field(default=None, description="sample seconds to log (static/none)")
    settle_s: float | None = Field(default=None, description="sample seconds not judged at the start")
    timeout_s: float | None = Field(default=None, description="step timeout, sample seconds")
    heat_c: float | None = Field(default=None, description="heat step: temperature rise that ends it, C")


class TimeLeft(_Out):
    """Time left (station/daemon/progress.py time_left); {"error": ...} alone when it cannot be estimated."""

    step_s: float | None = Field(default=None, description="sample seconds left in the step (estimate)")
    batch_s: float | None = Field(default=None, description="sample seconds left in the batch (estimate)")
    step_wall_s: float | None = Field(default=None, description="wall seconds left in the step (estimate)")
    batch_wall_s: float | None = Field(default=None, description="wall seconds left in the batch as the operator "
                                       "sees it: a countdown that never increases")
    raw_batch_wall_s: float | None = Field(default=None, description="the raw estimate of wall seconds left in the "
                                           "batch (may jump up and down)")
    estimated_at: float | None = Field(default=None, description="when estimated, Unix time s")
    n_steps: int | None = Field(default=None, description="number of steps of the profile")
    error: str | None = Field(default=None, description="why no estimate could be made (the status still answers)")


class StepRow(_Out):
    """One line of the batch's step list (station/daemon/progress.py step_rows)."""

    index: int = Field(description="step index; the last row is the end-of-batch analysis")
    name: str = Field(description="the step's name ('analysis' for the last row)")
    kind: str = one_of(row_kinds() + ("analysis",), "what the row is", nullable=False)
    position_name: str | None = Field(default=None, description="plate position of the step (null: analysis)")
    state: str = one_of(("pending", "running", "done", "skipped", "failed"), "where the step is", nullable=False)
    duration_s: float | None = Field(default=None, description="wall seconds it took (so far, when running); "
                                     "null when it did not start")
    expected_s: float | None = Field(default=None, description="wall seconds it is expected to take (estimate)")


class Prompt(_Out):
    """An open operator prompt (station/daemon/sequencer.py, web/views.py prompt_view)."""

    prompt_id: int = Field(description="the id to answer with (POST .../prompt)")
    id: int | None = Field(default=None, description="the same id, as the sequencer names it")
    kind: str | None = one_of(("turn_plate",), "what the operator is asked to do", default=None)
    text: str = Field(description="what to do, in words")
    position: int | None = Field(default=None, description="plate position index to turn to")
    position_name: str | None = Field(default=None, description="plate position name to turn to, e.g. N")
    step_index: int | None = Field(default=None, description="the profile step that waits for it")
    again: bool | None = Field(default=None, description="asked again while the step logs: after Done the DUTs do "
                               "not measure the position (docs/design.md section 4, 'Where the plate is')")
    reason: str | None = Field(default=None, description="why it is asked again, in words: 's03 still faces N 40 s "
                               "after Done', 's01, s02 face +y, not P (a wrong turn?)', 's01 left P and faces N'")
    direction: list[float] | None = Field(default=None, min_length=3, max_length=3, description="the board's static "
                                          "reading at that position, in g, in its own frame (unit vector x, y, z; "
                                          "contracts/positions.py): the axis that reads +1 g points up")


class Transition(_Out):
    """One state change of the batch's sequencer."""

    model_config = ConfigDict(extra="allow", serialize_by_alias=True, validate_by_name=True, validate_by_alias=True)

    time: float = Field(description="when, Unix time s")
    from_: str = Field(alias="from", description="state before (sequencer state, e.g. logging)")
    to: str = Field(description="state after")


class SlotStatus(DecisionFields):
    """One DUT of a batch: live (DutRun.status + web/views.py slot_view) or stored (web/db_repo.py)."""

    slot: str = Field(description="slot name from the config")
    link: str | None = Field(default=None, description="the board link, e.g. 'serial /dev/ttyUSB0'")
    serial: str | None = Field(default=None, description="the board's serial (null until identified)")
    label_serial: str | None = Field(default=None, description="serial scanned from the part's label at the start")
    route_flag: str | None = Field(default=None, description="in words, when the part is tested without the MES's "
                                   "yes (its route check gave no usable answer; the site's policy proceed_and_flag); "
                                   "'' or null otherwise (design 5.4)")
    sensor: str | None = Field(default=None, description="sensor type, e.g. LIS3DSH")
    state: str | None = Field(default=None, description="connecting, identified, running, done, faulted, interrupted")
    fault_reason: str | None = Field(default=None, description="the daemon's fault reason ('' when none)")
    segments: int = Field(default=0, description="segments logged in this batch")
    error: str | None = Field(default=None, description="fault reason, when faulted")
    temp_c: float | None = Field(default=None, description="not sent at present (always null): see the plot")
    samples: int | None = Field(default=None, description="samples received in this batch")
    sample_time_s: float | None = Field(default=None, description="board seconds logged in this batch")
    calibrator_state: str | None = Field(default=None, description="the live streaming calibrator's state "
                                         "(settling, discarding, averaging, waiting, ...)")
    link_stats: LinkStats | None = Field(default=None, description="the link's counters")
    result: CalibrationResultJson = Field(default=None, description="the calibration result (thermal or SFEM, "
                                          "per the profile's analysis); null until analysed")
    decision: DecisionOut | None = Field(default=None, description="the station's decision (without the passing "
                                         "checks); its fields are also given flat on the slot")
    program: LiveProgram | None = Field(default=None, description="program and verify: what the program step did")
    verification: LiveVerificationJson = Field(default=None, description="program and verify: verified E (thermal), "
                                               "or the cubic SFEM's residual on the board (SFEM, kind sfem-cubic)")
    program_verify: ProgramVerifyOut | None = Field(default=None, description="stored batch only: the stored "
                                                    "program-and-verify record")
    run_id: int | None = Field(default=None, description="this DUT's run in this batch")
    plot_url: str | None = Field(default=None, description="the plot of THIS run (/api/runs/{run_id}/plot.png): "
                                 "never the serial's latest run, so an interrupted DUT shows its own data")
    steps_done: int = Field(default=0, description="profile steps this DUT completed (progress dots)")
    waiting_for: str | None = Field(default=None, description="what this DUT's current step waits for; "
                                    "'plate at N' while it does not measure the confirmed position yet; "
                                    "'other DUTs' once it has what the step needs; null when not live")
    error_code: str | None = Field(default=None, description="the machine code of `error` "
                                   "(station/records/causes.py reason_code, e.g. "
                                   "'link_lost'): the page translates the cause by it; "
                                   "null when no rule names the words")

    words_codes: ClassVar[dict[str, str]] = {**DecisionFields.words_codes, "error_code": "error"}


class DecisionSummary(_Out):
    """Verdict and grade counts of a batch (station/decisions/verdicts.py summarize)."""

    judged: int = Field(default=0, description="DUTs judged")
    verdicts: dict[str, int] = Field(default_factory=dict, description="count per verdict (pass, marginal, fail, error)")
    grades: dict[str, int] = Field(default_factory=dict, description="count per grade")


class SortingEntry(_Out, CodedWords):
    """Which slot's board goes to which tray."""

    slot: str = Field(description="slot name")
    serial: str | None = Field(default=None, description="the board's serial")
    verdict: str | None = Field(default=None, description="pass | marginal | fail | error")
    grade: str | None = Field(default=None, description="bin")
    tray: str | None = Field(default=None, description="the tray to put the board in")
    reason: str | None = Field(default=None, description="plain words")
    attempt: int | None = Field(default=None, description="the serial's attempt number")
    reason_code: str | None = Field(default=None, description="the machine code of `reason` "
                                    "(station/records/causes.py reason_code, e.g. "
                                    "'link_lost'): the page translates the cause by it; "
                                    "null when no rule names the words")

    words_codes: ClassVar[dict[str, str]] = {"reason_code": "reason"}


class DutCounts(_Out):
    """DUTs per state: live ones as running."""

    running: int = Field(default=0, description="live DUTs (connecting, identified, running)")
    done: int = Field(default=0, description="DUTs that completed")
    faulted: int = Field(default=0, description="DUTs that faulted")
    interrupted: int = Field(default=0, description="DUTs the batch's end interrupted")


class SlotLive(_Out):
    """The slots' fast-changing figures as columns, one entry per slot in the order of `slots`
    (web/views.py slot_live). Why columns: the operator page polls them for every slot every two
    seconds (GET /api/batches/{id}?view=compact), and 64 objects that each repeat their field names
    would alone fill the 8 KiB the poll may take; `rev` tells the page when to fetch a slot's other
    fields again (GET /api/batches/{id}/slots), instead of polling them."""

    state: list[str | None] = Field(default_factory=list, description="each slot's state, as SlotStatus.state")
    segments: list[int | None] = Field(default_factory=list, description="segments logged, as SlotStatus.segments")
    samples: list[int | None] = Field(default_factory=list, description="samples received, as SlotStatus.samples")
    steps_done: list[int | None] = Field(default_factory=list, description="steps completed (progress dots), as "
                                         "SlotStatus.steps_done; null for a stored batch")
    waiting_for: list[str | None] = Field(default_factory=list, description="what the slot waits for, as "
                                          "SlotStatus.waiting_for")
    rev: list[str] = Field(default_factory=list, description="a short fingerprint of the slot's fields the compact "
                           "view leaves out (serial, label, sensor, run, fault, program, verification, verdict): "
                           "it changes when one of them does. Compare for equality only; it may differ after a "
                           "restart of the daemon")


class BatchStatus(TraceFields, CodedWords):
    """A batch: live from the daemon (station/daemon/batch_view.py status + progress.py batch_extras,
    through web/views.py batch_view), or, once the daemon no longer holds it, from the database
    (web/db_repo.py batch: `stored` true, no live fields)."""

    id: int = Field(description="batch id")
    profile: str | None = Field(default=None, description="profile name")
    operator: str | None = Field(default=None, description="the person who runs the batch")
    labels: dict[str, str] = Field(default_factory=dict, description="slot -> serial scanned from the part's label")
    state: str = Field(description="created | running | paused (waiting for the operator) | finished | aborted | "
                       "failed | interrupted")
    seq_state: str | None = Field(default=None, description="the sequencer's own state (connecting, step_setup, "
                                  "positioning, moving, waiting_operator, logging, programming, step_done, "
                                  "analysing, or an end state); live only")
    step_index: int | None = Field(default=None, description="index of the current step (-1 before the first)")
    step: StepInfo | None = Field(default=None, description="the current step")
    n_steps: int | None = Field(default=None, description="number of steps of the profile; live only")
    steps: list[StepRow] = Field(default_factory=list, description="every step and the analysis with its state and "
                                 "wall durations; live only")
    progress: float | None = Field(default=None, description="fraction of the batch done by wall "
                                   "time (0..1, never decreases); 1 once finished, null after another end")
    position: int | None = Field(default=None, description="plate position index now (null: moving or unknown)")
    position_name: str | None = Field(default=None, description="plate position name now")
    sample_time_s: float | None = Field(default=None, description="the boards' sample clock in this batch, s")
    step_elapsed_s: float | None = Field(default=None, description="sample seconds the current step has logged")
    slots: list[SlotStatus] = Field(default_factory=list, description="every DUT of the batch")
    overload: Overload | None = Field(default=None, description="live only: is the station keeping up with the "
                                      "batch's boards (an alarm in words when it is not)")
    error: str | None = Field(default=None, description="why the batch failed or was aborted")
    prompt: Prompt | None = Field(default=None, description="the open operator prompt, if any")
    lamp_on: bool | None = Field(default=None, description="what the station last commanded")
    lamp_state: str | None = one_of(("on", "off", "unknown"), "'unknown' while the lamp relay does not answer reads "
                                    "or writes", default=None)
    lamp_relay_error: str | None = Field(default=None, description="the relay's last error, while it fails")
    lamp_on_time_s: float | None = Field(default=None, description="wall seconds the lamp has been on in this batch")
    decision: DecisionSummary | None = Field(default=None, description="verdict and grade counts")
    sorting: list[SortingEntry] = Field(default=[], description="which slot goes to which tray")
    time_left: TimeLeft | None = Field(default=None, description="estimated time left; live only")
    started: float | None = Field(default=None, description="when the batch started, Unix time s; live only")
    ended: float | None = Field(default=None, description="when it ended, Unix time s (null while running); live only")
    elapsed_s: float | None = Field(default=None, description="wall seconds since the batch started (to its end)")
    waiting_for: str | None = Field(
        default=None, description="what the current step waits for: boards, fixture, operator, chamber, "
        "temperature rise, static dwell, segment, dwell, programming, analysis; null once ended")
    ended_by: str | None = Field(default=None, description="who ended the batch: the token's name for an abort, "
                                 "'station' for an end it reached itself, 'daemon' for a shutdown; null while running")
    ended_at: str | None = Field(default=None, description="when the batch ended (RFC 3339 UTC); null while running")
    analysis: str | None = Field(default=None, description="the profile's analysis: thermal, sfem or none")
    note: str | None = Field(default=None, description="what the profile does not give, e.g. no calibration result "
                             "for analysis 'none' (validation)")
    counts: DutCounts | None = Field(default=None, description="DUTs per state")
    transitions: list[Transition] = Field(default_factory=list, description="the sequencer's state changes; live only")
    current_step: StepRow | None = Field(default=None, description="the row of `steps` that is running now (null "
                                         "when none is): the compact view carries it instead of the whole list")
    slot_live: SlotLive | None = Field(default=None, description="the slots' fast-changing figures as columns in the "
                                       "order of `slots` (what the compact view carries per slot)")
    # a batch the daemon no longer holds, from the database (web/db_repo.py batch)
    stored: bool | None = Field(default=None, description="true: read from the database (the daemon no longer "
                                "holds the batch, e.g. after a restart); absent for a live batch")
    station: str | None = Field(default=None, description="stored only: the station that ran it (config `name`)")
    reason: str | None = Field(default=None, description="stored only: the stored end reason ('' when none)")
    last_completed_step: int | None = Field(default=None, description="stored only: what a resume restarts after")
    schema_version: str | None = Field(default=None, description="stored only: database schema revision it was "
                                       "written with")
    created_at: str | None = Field(default=None, description="stored only: when it was created (ISO 8601 UTC)")
    replay_of: str | None = Field(default=None, description="stored only: the source of a replay batch; null for "
                                  "real parts")
    replay_diff: dict | None = free_form(
        "stored only: a replay's comparison with its recording, as GET /api/replays/{batch_id} `diff`", default=None)
    step_windows: dict[str, dict[str, list[float | None]]] = Field(
        default_factory=dict, description="stored only: {step index: {slot: [from, to]}} board seconds of every "
        "completed step (resume, SFEM windows)")
    error_code: str | None = Field(default=None, description="the machine code of `error` "
                                   "(station/records/causes.py reason_code, e.g. "
                                   "'cannot_do_it_operator'); null when no rule names the words")

    words_codes: ClassVar[dict[str, str]] = {"error_code": "error"}


class SlotOut(_Out, CodedWords):
    """A slot of the station (station/daemon/slots.py slots_status + web/views.py slot_view)."""

    slot: str = Field(description="slot name from the config")
    name: str | None = Field(default=None, description="the same name")
    link: str | None = Field(default=None, description="the board link, e.g. 'serial /dev/ttyUSB0'")
    kind: str | None = Field(default=None, description="not sent at present (always null): see `link`")
    state: str | None = Field(default=None, description="the slot: identified (ready; also after its DUT faulted in "
                              "a batch, once the batch ended and the board answered), busy, faulted (its board "
                              "does not answer: fault_reason says why; a batch may still take it and tries to "
                              "connect it again), disconnected")
    serial: str | None = Field(default=None, description="the board's serial once identified")
    sensor: str | None = Field(default=None, description="sensor type")
    batch_id: int | None = Field(default=None, description="the batch it belongs to (null: none)")
    run_state: str | None = Field(default=None, description="its DUT run's state in that batch")
    run_id: int | None = Field(default=None, description="its DUT run in that batch")
    plot_url: str | None = Field(default=None, description="the plot of that run")
    segments: int = Field(default=0, description="segments logged (0 outside a batch's status)")
    fault_reason: str | None = Field(default=None, description="the daemon's fault reason ('' when none)")
    error: str | None = Field(default=None, description="fault reason, when faulted")
    link_stats: LinkStats | None = Field(default=None, description="the link's counters")
    label_serial: str | None = Field(default=None, description="serial scanned from the part's label for this slot")
    identity_problem: str | None = Field(default=None, description="why a batch would stop this identified slot before "
                                         "heating (design 3.1): a serial another identified slot reports too, an "
                                         "empty or invalid one; null when none")
    error_code: str | None = Field(default=None, description="the machine code of `error` "
                                   "(station/records/causes.py reason_code, e.g. "
                                   "'link_lost'): the page translates the cause by it; "
                                   "null when no rule names the words")

    words_codes: ClassVar[dict[str, str]] = {"error_code": "error"}


class LampHealth(_Out):
    """The lamp as the station sees it (station/daemon/supervisor.py lamp_status)."""

    state: str | None = one_of(("on", "off", "unknown"), "the relay's real state", default=None)
    on_commanded: bool | None = Field(default=None, description="what the station last commanded")
    relay_error: str | None = Field(default=None, description="the relay's last error, while it fails")
    watchdog_s: float | None = Field(default=None, description="lamp watchdog, s (0: not armed)")
    trip: str | None = Field(default=None, description="why the safety tripped, if it did")


class Forwarding(_Out):
    events: int = Field(description="events (samples blocks, segments, results, verdicts...) waiting in the "
                                    "station's journal, durable on the station")
    batches: dict[int, int] = Field(default_factory=dict, description="batch id -> events of it waiting")


class Health(_Out):
    status: str = Field(description="'ok' while the web app answers")
    version: str = Field(description="station software version")
    time: float = Field(description="the station's clock, Unix time s")
    db: str | None = Field(default=None, description="'ok', 'none' (no database), 'forwarding: N events ...' while "
                                                      "the station's journal is forwarded to a database that answers "
                                                      "again, or 'error: ...' (e.g. 'error: database not answering "
                                                      "since 12 s'); never waits on the database")
    forwarding: Forwarding | None = Field(default=None, description="what waits in the station's journal to be "
                                                                    "forwarded to the database; null without a station")
    lamp: LampHealth | None = Field(default=None, description="the lamp; null without a station")
    intake: Overload | None = Field(default=None, description="is the station keeping up with its boards; null "
                                    "without a station")
