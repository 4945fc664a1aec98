"""DPO-FLAT's policy: DIPPER's squashed-Gaussian actor (no critic), acting on primitive actions instead of subgoals.

Goal envs have Dict observations, so both names map to the same class, which handles Dict and Box observations.
"""

from sb3_dipper.dipper.policies import DIPPERPolicy

MlpPolicy = DIPPERPolicy
MultiInputPolicy = DIPPERPolicy

__all__ = ["DIPPERPolicy", "MlpPolicy", "MultiInputPolicy"]
