"""Deciding (design 8): limits as data, verdicts, grades and trays, and the moment they become final.

- measurements.py  every measurement declared once: name, unit, axes, its 1-sigma, what a limit on it
                   means, the operator's and the records' words (everything below reads it)
- limits.py        products and their versioned limit sets (station TOML `[products.NAME]`)
- readings.py      pure: what a run stored -> Measurements; what a profile requires
- judging.py       pure: one measurement against one limit, in the operator's words
- checks.py        pure: the verdict's checks, one registered object each (a new check: one class,
                   one `register`)
- sfem_checks.py   pure: what the verdict reads from an SFEM record, and its model check's words
- verdicts.py      pure: measurements + limits -> verdict, grade, tray; a run's final verdict
- moment.py        the thin adapter to the daemon: judge every run once, when it ends
- verdict_context.py  what the moment reads of the station and a batch, typed (no attribute by name)
- limits_audit.py  limit-set changes become audit rows at daemon start
"""
