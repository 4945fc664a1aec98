from sb3_dipper.hac.hac import HAC, ClippedSAC
from sb3_dipper.hac.policies import MlpPolicy, MultiInputPolicy

__all__ = ["HAC", "ClippedSAC", "MlpPolicy", "MultiInputPolicy"]
