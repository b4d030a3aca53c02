"""`python -m jsphere.cli`: the command line."""

import sys

from .app import console

if __name__ == "__main__":
    sys.exit(console())
