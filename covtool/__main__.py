"""``python -m covtool``: the same command line as ``covtool``."""

import sys

from .cli import main

sys.exit(main())
