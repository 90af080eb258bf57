"""``python -m magkf``: the command line."""

import sys

from .cli import main

if __name__ == "__main__":  # not when a spawned process imports it (``diagnostics.chunked_run``)
    sys.exit(main())
