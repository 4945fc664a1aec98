"""RAPS's higher level is an SB3 SAC over ``[arguments, selector]``; goal envs have Dict observations, so both names map
to SAC's ``MultiInputPolicy``.

As SB3's attribute ``model.policy`` this is the *higher* level: ``model.policy.predict`` returns a higher-level action in
``[-1, 1]^d`` (a primitive's arguments and selector), not a primitive action. ``model.predict`` runs the chosen primitives
too, and ``model.export_policy()`` returns both as a :class:`~sb3_dipper.common.hierarchical_policy.HierarchicalPolicy`.
"""

from stable_baselines3.sac.policies import MultiInputPolicy

MlpPolicy = MultiInputPolicy

__all__ = ["MlpPolicy", "MultiInputPolicy"]
