from sb3_dipper.dipper.dipper import DIPPER
from sb3_dipper.dipper.policies import DIPPERPolicy, MlpPolicy, MultiInputPolicy

__all__ = ["DIPPER", "DIPPERPolicy", "MlpPolicy", "MultiInputPolicy"]
