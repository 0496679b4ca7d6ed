"""The `station` command line (design 5.2, docs/cli.md): the top floor (tests/test_layers.py).

`cli.main.main()` is the `station` script (also `python -m cli`); one module per command in
cli/commands/. It starts the daemon (station/), the web app (web/) and the simulated demo, so it may
import any floor below; nothing below imports it.
"""
