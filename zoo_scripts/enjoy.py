"""rl-zoo3's enjoy with this package's algorithms: ``python zoo_scripts/enjoy.py --algo dipper --env ... -f logs/``.

Hierarchical models load with ``env=None`` and act through ``predict`` with their option state; videos record headless
with ``MUJOCO_GL=egl``.
"""

import os
import sys

os.environ.setdefault("MUJOCO_GL", "egl")

from sb3_dipper.zoo import main

if __name__ == "__main__":
    sys.argv.insert(1, "enjoy")
    main()
