from sb3_dipper.saga.policies import MlpPolicy, MultiInputPolicy, SubgoalDiscriminator
from sb3_dipper.saga.saga import SAGA, AdversarialSAC

__all__ = ["SAGA", "AdversarialSAC", "MlpPolicy", "MultiInputPolicy", "SubgoalDiscriminator"]
