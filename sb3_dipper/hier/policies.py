"""HIER's higher level is an SB3 SAC; goal envs have Dict observations, so both names map to SAC's MultiInputPolicy.

As SB3's attribute ``model.policy`` this is the *higher* level: ``model.policy.predict`` returns a higher-level action in
``[-1, 1]^d`` (a subgoal; ``model.subgoal_space.to_world`` maps it to the goal space), not a primitive action.
``model.predict`` runs both levels, and ``model.export_policy()`` returns them as a
:class:`~sb3_dipper.common.hierarchical_policy.HierarchicalPolicy` that acts without the algorithm. The same holds for
PIPER and SAGA, which use this policy.
"""

from stable_baselines3.sac.policies import MultiInputPolicy

MlpPolicy = MultiInputPolicy

__all__ = ["MlpPolicy", "MultiInputPolicy"]
