"""The running station: the `Station` facade (supervisor.py) and the parts it wires.

Links (instruments.py) and storage (storage.py) are opened at start. Per batch, one state machine
(sequencer.py, its table in states.py, each DUT's record in dut_run.py, its status in
batch_view.py) drives the plate and the lamp (safety.py: LampGuard) while the slots (slots.py)
stream and one pump per DUT takes the samples in (intake.py). At the end the run's end (run_end.py)
analyses (results.py), programs and verifies (program_verify.py) and hands every run to the
verdict's moment (station/decisions/moment.py). progress.py estimates the time left.
"""
