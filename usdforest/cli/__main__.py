"""``python -m usdforest.cli``: the command line, as the console script runs it."""

from usdforest.cli import main

main()
