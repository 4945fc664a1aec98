"""RAPS's higher level is an SB3 SAC over ``[arguments, selector]``; goal envs have Dict observations, so both names map
to SAC's ``MultiInputPolicy``."""

from stable_baselines3.sac.policies import MultiInputPolicy

MlpPolicy = MultiInputPolicy

__all__ = ["MlpPolicy", "MultiInputPolicy"]
