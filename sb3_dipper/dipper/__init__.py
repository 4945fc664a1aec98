from sb3_dipper.dipper.dipper import DEFAULT_SWITCH_KWARGS, DIPPER
from sb3_dipper.dipper.policies import DIPPERPolicy, MlpPolicy, MultiInputPolicy

__all__ = ["DEFAULT_SWITCH_KWARGS", "DIPPER", "DIPPERPolicy", "MlpPolicy", "MultiInputPolicy"]
