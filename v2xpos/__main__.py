"""``python -m v2xpos ...``: the same as the ``v2xpos`` command."""
import sys

from v2xpos.cli import main

if __name__ == "__main__":
    sys.exit(main())
