"""Entry point of ``make bench``."""

import sys

from viewloc_bench.cli import main

sys.exit(main())
