"""``python -m servotune``: the same as the ``servotune`` command."""

import sys

from servotune.cli import main

sys.exit(main())
