"""The running station: the `Station` facade (supervisor.py) and the parts it wires.

One sequencer per batch (sequencer.py) drives the plate, the lamp (safety.py: LampGuard) and the
DUTs' pumps (slots.py); the run's end (run_end.py) analyses, programs and verifies
(program_verify.py) and hands every run to the verdict's moment (station/decisions/moment.py).
"""
