"""``python -m qpnso.cli``: the ``qpnso`` command line."""

import sys

from qpnso.cli import main

if __name__ == "__main__":
    sys.exit(main())
