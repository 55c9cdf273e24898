"""``python -m tdfd.autofocus ...``: the same as ``tdfd autofocus ...``."""

import sys

from ..cli import main

sys.exit(main(["autofocus", *sys.argv[1:]]))
