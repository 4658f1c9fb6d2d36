"""``python -m covtool``: the same command line as ``covtool``."""

import sys

from covtool.cli import main

sys.exit(main())
