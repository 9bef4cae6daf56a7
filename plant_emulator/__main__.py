"""`python -m plant_emulator [--scenario FILE|NAME] [--seed N] [--speedup X]` (see process.py)."""

import sys

from .process import main

if __name__ == "__main__":
    sys.exit(main())
