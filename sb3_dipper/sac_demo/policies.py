"""SACDemo's policy: SB3's SAC policy. Goal envs have Dict observations, so both names map to SAC's
``MultiInputPolicy``."""

from stable_baselines3.sac.policies import MultiInputPolicy

MlpPolicy = MultiInputPolicy

__all__ = ["MlpPolicy", "MultiInputPolicy"]
