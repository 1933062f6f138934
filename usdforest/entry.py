"""The console script: Ctrl-C while the heavy modules load still ends in one line.

``usdforest.cli`` imports numpy, typer and rich before its own handler can catch an interrupt;
this small module wraps that import.
"""

from __future__ import annotations

import sys


def main() -> None:
    try:
        from .cli import main as cli_main
    except KeyboardInterrupt:
        sys.stderr.write("error: interrupted\n")
        sys.exit(130)
    cli_main()


if __name__ == "__main__":
    main()
