"""Deciding (design 8): limits as data, verdicts, grades and trays, and the moment they become final.

- limits.py        products and their versioned limit sets (station TOML `[products.NAME]`)
- verdicts.py      pure: measurements + limits -> verdict, grade, tray; a run's final verdict
- moment.py        the thin adapter to the daemon: judge every run once, when it ends
- verdict_context.py  what the moment reads of the station and a batch, typed (no attribute by name)
- limits_audit.py  limit-set changes become audit rows at daemon start
"""
