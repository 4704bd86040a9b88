"""``python -m selpath``: the command line, as the ``selpath`` script runs it."""

from selpath.pipeline.cli import main

main()
