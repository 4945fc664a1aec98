"""Moved to ``zoo_scripts/research/benchmark_envs.py`` with the other research tools; this forwarder warns and runs it."""

import runpy
import sys
import warnings
from pathlib import Path

MOVED_TO = Path(__file__).resolve().parent / "research" / "benchmark_envs.py"

warnings.warn(f"zoo_scripts/{MOVED_TO.name} moved to zoo_scripts/research/{MOVED_TO.name}: use that path", FutureWarning)
if __name__ == "__main__":
    runpy.run_path(str(MOVED_TO), run_name="__main__")
else:  # imported as a module: the moved one's names
    sys.path.insert(0, str(MOVED_TO.parents[1]))
    from research.benchmark_envs import *  # noqa: F403
