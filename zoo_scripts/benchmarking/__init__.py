"""The benchmarks behind ``zoo_scripts/benchmark.py``, its command line: learning runs (:mod:`.run`), their report and
the BENCHMARKS.md sections (:mod:`.report`), and training speed (:mod:`.profile`).

The scripts import each other from the ``zoo_scripts`` folder (``plot``, ``configs``), as a script run from there
does; imported from elsewhere (``zoo_scripts.benchmarking``, in the tests), the package puts that folder on the path.
"""

import sys
from pathlib import Path

SCRIPTS = Path(__file__).resolve().parents[1]
if str(SCRIPTS) not in sys.path:
    sys.path.insert(0, str(SCRIPTS))
