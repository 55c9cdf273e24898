"""``python -m data_synth``: see :mod:`data_synth.cli`."""

import sys

from .cli import main

if __name__ == "__main__":
    sys.exit(main())
