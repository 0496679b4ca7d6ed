"""The ground floor: data contracts every other package stands on.

What a board reports (identity, sample blocks), what the daemon publishes (events), the log format
of design 5.1 and its checks, the plate's positions, safe file names and the recorded streams a
replay plays back. drivers/, db/, station/ and web/ all import from here; this package imports
none of them (tests/test_layers.py checks it), so a contract changes in one place.
"""
