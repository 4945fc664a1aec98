from sb3_dipper.raps.policies import MlpPolicy, MultiInputPolicy
from sb3_dipper.raps.primitives import PrimitiveLibrary, register_primitive_library
from sb3_dipper.raps.raps import RAPS

__all__ = ["RAPS", "MlpPolicy", "MultiInputPolicy", "PrimitiveLibrary", "register_primitive_library"]
