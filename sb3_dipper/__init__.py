import os

from sb3_dipper.common.subgoals import SubgoalSpace, register_subgoal_space
from sb3_dipper.dipper import DIPPER
from sb3_dipper.hier import HIER
from sb3_dipper.piper import PIPER
from sb3_dipper.saga import SAGA
from sb3_dipper.envs import register_envs

register_envs()

with open(os.path.join(os.path.dirname(__file__), "version.txt")) as file_handler:
    __version__ = file_handler.read().strip()

__all__ = ["DIPPER", "HIER", "PIPER", "SAGA", "SubgoalSpace", "register_subgoal_space"]
