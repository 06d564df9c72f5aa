"""`python -m pressurepose ...`: the `pressurepose` command line (`pressurepose.cli`)."""

import sys

from pressurepose.cli import main

sys.exit(main())
