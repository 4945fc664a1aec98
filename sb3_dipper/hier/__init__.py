from sb3_dipper.hier.hier import HIER
from sb3_dipper.hier.policies import MlpPolicy, MultiInputPolicy

__all__ = ["HIER", "MlpPolicy", "MultiInputPolicy"]
