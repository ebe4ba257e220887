"""``python -m certpose``: the same as the ``certpose`` script."""

from certpose.cli import run

run()
