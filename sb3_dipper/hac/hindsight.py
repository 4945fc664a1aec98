"""HAC's transition rules as pure functions (Levy et al., ICLR 2019, Section 4), tested on hand-made data.

Notation: a higher-level window is the ``T`` options of one base episode (HAC's ``H`` attempts of the top level). Option
``t`` starts in ``s_t``, proposes the unit action ``u_t`` (subgoal ``g_t``) and ends in ``s_{t+1}`` with achieved goal
``ag_{t+1}`` and projected achieved subgoal ``p(s_{t+1})``. Rewards follow HAC: ``-1`` until a goal is reached, ``0``
when it is, and a reached goal ends bootstrapping (``done``, HAC's ``finished``: gamma 0 for that target).

- Hindsight action (Section 4.2): the stored action is ``u_t`` if the lower level reached ``g_t``, otherwise the
  subgoal it did reach, ``p(s_{t+1})`` in unit coordinates, so the transition looks as if the lower level were optimal.
- Hindsight goal (Section 4.3): after the window, some achieved goals ``ag_{i+1}`` become goals of *every* transition of
  the window (the official code loops over all of them, an "episode" strategy), with reward and ``done`` recomputed.
- Subgoal testing (Section 4.4): a tested subgoal that the greedy lower level missed within its ``K`` steps gives the
  proposing level the transition ``(s_t, u_t, -T, s_{t+1})`` with ``done`` (no bootstrap): ``-T``, the proposing level's
  horizon, is the lowest value its critic (bounded to ``[-T, 0]``) can take.
- The DIPPER authors' simplified HAC (``paper_compat``): every option is stored twice, with the proposed and with the
  reached subgoal as action, both relabelled with HER's "future" goals, and every option of a greedy episode once more
  with the proposed subgoal and reward ``-T``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

GoalReachedFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


def hindsight_actions(proposed: np.ndarray, achieved: np.ndarray, subgoal_reached: np.ndarray) -> np.ndarray:
    """HAC's hindsight action: the proposed unit action where its subgoal was reached, else the achieved subgoal.

    :param proposed: ``(N, d)`` proposed actions ``u_t`` in ``[-1, 1]^d``
    :param achieved: ``(N, d)`` achieved subgoals ``p(s_{t+1})`` in unit coordinates
    :param subgoal_reached: ``(N,)`` whether the lower level reached ``g_t``
    """
    return np.where(np.asarray(subgoal_reached, dtype=bool)[:, None], proposed, achieved).astype(np.float32)


def goal_rewards(achieved_goals: np.ndarray, goals: np.ndarray, goal_reached: GoalReachedFn) -> tuple[np.ndarray, np.ndarray]:
    """HAC's sparse reward and termination: ``(-1 + reached, reached)`` for each ``(ag_{t+1}, goal)`` row."""
    reached = np.asarray(goal_reached(achieved_goals, goals), dtype=bool)
    return reached.astype(np.float32) - 1.0, reached.astype(np.float32)


def hac_goal_indices(n_transitions: int, n_goals: int, rng: np.random.Generator) -> np.ndarray:
    """Which achieved goals of a window become hindsight goals (HAC's ``finalize_goal_replay``).

    The last transition's achieved goal always; ``n_goals - 1`` more drawn uniformly (with replacement) from the window;
    at most ``n_transitions`` in all.
    """
    n_goals = min(n_goals, n_transitions)
    if n_goals <= 0:
        return np.zeros(0, dtype=np.int64)
    others = rng.integers(n_transitions, size=n_goals - 1)
    return np.append(others, n_transitions - 1).astype(np.int64)


def hac_goal_pairs(n_transitions: int, goal_indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(transition, goal)`` index pairs of HAC's relabelling: every transition of the window with every chosen goal."""
    transitions = np.tile(np.arange(n_transitions), len(goal_indices))
    goals = np.repeat(goal_indices, n_transitions)
    return transitions, goals


def future_goal_pairs(n_transitions: int, n_goals: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``(transition, goal)`` index pairs of HER's "future" strategy: ``n_goals`` goals from ``[t, T)`` per transition ``t``.

    The DIPPER authors' higher level relabels this way (their HER with ``k = 4``, relabelling probability 0.8).
    """
    transitions = np.repeat(np.arange(n_transitions), n_goals)
    goals = transitions + np.floor(rng.random(transitions.size) * (n_transitions - transitions)).astype(np.int64)
    return transitions, goals


def relabel_goals(
    next_achieved_goals: np.ndarray, transitions: np.ndarray, goal_indices: np.ndarray, goal_reached: GoalReachedFn
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hindsight goal transitions: the goal of transition ``transitions[j]`` becomes ``ag`` after option ``goal_indices[j]``.

    :param next_achieved_goals: ``(T, G)`` achieved goal at the end of each option of the window
    :param transitions: ``(N,)`` transitions to relabel
    :param goal_indices: ``(N,)`` options whose achieved goal is the new goal
    :param goal_reached: vectorised ``goal_reached(achieved, desired)``
    :return: new goals ``(N, G)``, rewards ``(N,)`` and ``done`` flags ``(N,)``, recomputed for the new goals
    """
    goals = next_achieved_goals[goal_indices]
    rewards, dones = goal_rewards(next_achieved_goals[transitions], goals, goal_reached)
    return goals, rewards, dones


def penalized_subgoals(tested: np.ndarray, subgoal_reached: np.ndarray, option_completed: np.ndarray) -> np.ndarray:
    """Which options earn HAC's subgoal penalty: tested, missed, and given all ``K`` steps (HAC's ``maxed_out``).

    An option the base episode cut short is not penalised: the lower level did not use up its attempts.
    """
    return np.asarray(tested, dtype=bool) & ~np.asarray(subgoal_reached, dtype=bool) & np.asarray(option_completed, dtype=bool)


def penalty_transitions(n_penalized: int, penalty: float) -> tuple[np.ndarray, np.ndarray]:
    """Rewards and ``done`` flags of penalty transitions: reward ``-penalty``, no bootstrap (gamma 0 on the target)."""
    return np.full(n_penalized, -penalty, dtype=np.float32), np.ones(n_penalized, dtype=np.float32)


def greedy_episode_rewards(n_transitions: int, high_steps: int) -> np.ndarray:
    """The DIPPER authors' HAC: every transition of a greedy episode gets ``-T``, whether or not its subgoal was reached.

    (Their rollout stores these with the proposed actions and no termination.)
    """
    return np.full(n_transitions, -float(high_steps), dtype=np.float32)
