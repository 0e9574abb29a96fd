"""``python -m servotune``: the same as the ``servotune`` command."""

import sys

from servotune.cli import main

if __name__ == "__main__":  # not when multiprocessing's spawn imports it
    sys.exit(main())
