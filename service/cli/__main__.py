"""`python -m service.cli`: the `ripplecal` command."""

import sys

from service.cli import main

sys.exit(main())
