"""Replay recorded batches through simulated boards (`station replay`).

    recording.py  what was recorded: each DUT's raw counts, identity, clock, plate state, outcome
    compare.py    pure: the recorded outcome against the replayed one (tolerances, summary, exit)
    runner.py     the replay itself: ReplayStation (drivers/sim/replay.py) + the real daemon

Data flow is the station's own: a recording becomes simulated boards on real links (pty serial,
slcan CAN, Modbus relay/fixture), the unchanged daemon calibrates and judges them, and the
outcome is compared with the recorded one.
"""
