"""``python -m certpose``: the same as the ``certpose`` script."""

import sys

from certpose.cli import main

sys.exit(main())
