"""`python -m cli ARGS`: the `station` command without the installed script."""

import sys

from cli.main import main

sys.exit(main())
