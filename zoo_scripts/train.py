"""rl-zoo3's train with this package's algorithms: ``python zoo_scripts/train.py --algo dipper --env PointMazeFourRooms-v0``.

Takes rl-zoo3's own flags; ``--conf-file`` defaults to ``hyperparams/<algo>.yml`` (see :mod:`sb3_dipper.zoo`).
"""

import sys

from sb3_dipper.zoo import main

if __name__ == "__main__":
    sys.argv.insert(1, "train")
    main()
