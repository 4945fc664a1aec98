from sb3_dipper.sac_demo.policies import MlpPolicy, MultiInputPolicy
from sb3_dipper.sac_demo.sac_demo import SACDemo

__all__ = ["MlpPolicy", "MultiInputPolicy", "SACDemo"]
