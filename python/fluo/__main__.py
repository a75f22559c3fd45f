"""``python -m fluo``: the same command line as the ``fluo`` console script."""

import sys

from .cli import main

sys.exit(main())
