from sb3_dipper.dac.dac import DAC
from sb3_dipper.dac.policies import Discriminator, MlpPolicy, MultiInputPolicy

__all__ = ["DAC", "Discriminator", "MlpPolicy", "MultiInputPolicy"]
