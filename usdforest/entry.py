"""The console script: a Ctrl-C or SIGTERM at any moment once usdforest's code runs ends in one
line (exit 130, or 143 for SIGTERM).

``usdforest.cli`` imports numpy, typer and rich before its own handler can catch an interrupt,
and between that import and the handler there is a gap; this small module covers both.
What it cannot cover is the interpreter's own start-up (``site`` and ``.pth`` files, the first
10-30 ms): a Ctrl-C there is Python's, it may print Python's traceback, and nothing has been
written yet.
"""

from __future__ import annotations

import sys


def main() -> None:
    try:
        # inside the try: a Ctrl-C while ``signals`` itself loads (it imports typing) is
        # one line too, not a traceback through this file
        from usdforest import signals

        signals.terminate_as_interrupt()
        from usdforest.cli import main as cli_main

        cli_main()
    except KeyboardInterrupt:
        done = sys.modules.get("usdforest.signals")
        stopped = getattr(done, "stopped", None)
        line, status = stopped() if stopped else ("error: interrupted", 130)
        sys.stderr.write(line + "\n")
        sys.exit(status)


if __name__ == "__main__":
    main()
