import os

from sb3_dipper.common.subgoals import SubgoalSpace, register_subgoal_space
from sb3_dipper.dac import DAC
from sb3_dipper.dipper import DIPPER
from sb3_dipper.dpo_flat import DPOFlat
from sb3_dipper.envs import register_envs
from sb3_dipper.hac import HAC
from sb3_dipper.hier import HIER
from sb3_dipper.piper import PIPER
from sb3_dipper.raps import RAPS
from sb3_dipper.sac_demo import SACDemo
from sb3_dipper.saga import SAGA

register_envs()

with open(os.path.join(os.path.dirname(__file__), "version.txt")) as file_handler:
    __version__ = file_handler.read().strip()

__all__ = [
    "DAC",
    "DIPPER",
    "HAC",
    "HIER",
    "PIPER",
    "RAPS",
    "SAGA",
    "DPOFlat",
    "SACDemo",
    "SubgoalSpace",
    "register_subgoal_space",
]
