"""Record how long each test and test file took, from a pytest JUnit XML report.

``python tests/durations.py REPORT.xml`` writes ``tests/durations.json``: each file's seconds
(setup, call and teardown of its tests), each test of a second or more, the run's date and
commit. The suite reads it (``conftest.py``) to hand the longest files out first and to mark
the tests of at least :data:`HEAVY_SECONDS` ``heavy`` (``make test-quick`` leaves them out).
``make test-durations`` runs the whole suite and writes it.
"""

from __future__ import annotations

import datetime
import json
import subprocess
import sys
import xml.etree.ElementTree as ET
from collections import defaultdict
from pathlib import Path

HERE = Path(__file__).resolve().parent
OUT = HERE / "durations.json"
HEAVY_SECONDS = 5.0  # a test this long or longer is left out of `make test-quick`


def node_id(case: ET.Element) -> str:
    """``tests/test_x.py::name`` of a JUnit ``testcase`` (classname ``tests.test_x``)."""
    module = case.get("classname", "").replace(".", "/")
    return f"{module}.py::{case.get('name')}"


def read_report(path: Path) -> tuple[dict[str, float], dict[str, float]]:
    """``(per file, per test)`` seconds of the report at ``path``."""
    files: dict[str, float] = defaultdict(float)
    tests: dict[str, float] = {}
    for case in ET.parse(path).iter("testcase"):
        seconds = float(case.get("time", 0.0))
        nid = node_id(case)
        files[nid.split("::")[0]] += seconds
        tests[nid] = seconds
    return dict(files), tests


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: python tests/durations.py REPORT.xml", file=sys.stderr)
        return 2
    files, tests = read_report(Path(argv[0]))
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True, cwd=HERE, check=False).stdout.strip()  # fmt: skip
    record = {
        "measured": datetime.date.today().isoformat(),
        "commit": commit,
        "total_seconds": round(sum(files.values()), 1),
        "files": {k: round(v, 1) for k, v in sorted(files.items(), key=lambda kv: -kv[1])},
        "tests": {k: round(v, 1) for k, v in sorted(tests.items()) if v >= 1.0},
    }
    OUT.write_text(json.dumps(record, indent=1) + "\n")
    heavy = sum(v >= HEAVY_SECONDS for v in tests.values())
    print(f"{OUT.name}: {len(tests)} tests, {heavy} of {HEAVY_SECONDS:g} s or more, "
          f"{record['total_seconds']:.0f} s in all")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
