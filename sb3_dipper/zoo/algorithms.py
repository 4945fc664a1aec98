"""Our algorithms under their zoo names, and the hyperparameter files the zoo trains them with.

A module of its own, below everything else of :mod:`sb3_dipper.zoo`: the run-configuration loader
(:mod:`sb3_dipper.zoo.run_config`) builds models from these names without importing the zoo's command line.
"""

from __future__ import annotations

import sys
from pathlib import Path

from stable_baselines3.common.base_class import BaseAlgorithm

from sb3_dipper.dac import DAC
from sb3_dipper.dipper import DIPPER
from sb3_dipper.dpo_flat import DPOFlat
from sb3_dipper.hac import HAC
from sb3_dipper.hier import HIER
from sb3_dipper.piper import PIPER
from sb3_dipper.raps import RAPS
from sb3_dipper.sac_demo import SACDemo
from sb3_dipper.saga import SAGA

# Zoo names: the same class can appear under several names so that comparison plots show each as its own line.
ZOO_ALGORITHMS: dict[str, type[BaseAlgorithm]] = {
    "dipper": DIPPER,
    "dipper_paper": DIPPER,
    "dipper_nov": DIPPER,
    "hier": HIER,
    "piper": PIPER,
    "saga": SAGA,
    "hac": HAC,
    "raps": RAPS,
    "dac": DAC,
    "dpo_flat": DPOFlat,
    "sac_demo": SACDemo,
}


def hyperparams_dir() -> Path:
    """Our hyperparameter files: beside the package in a checkout, under ``<prefix>/share/sb3-dipper`` when installed."""
    checkout = Path(__file__).resolve().parents[2] / "hyperparams"
    if checkout.is_dir():
        return checkout
    return Path(sys.prefix) / "share" / "sb3-dipper" / "hyperparams"
