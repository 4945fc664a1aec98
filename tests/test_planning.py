"""Planning over achieved states: the voxel graph, shortest paths that stitch trajectories, waypoints, and who proposes
DIPPER's subgoals with the subgoal planner (the planner's share, zoo_scripts/research/planner_share.py), and DIPPER's planning
parameters before ``planner_kwargs``."""

import itertools
import json
import math
import re
import subprocess
import sys
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import configure
from stable_baselines3.common.save_util import data_to_json
from stable_baselines3.common.utils import obs_as_tensor
from stable_baselines3.common.vec_env import VecNormalize

from sb3_dipper import DIPPER, HIER, RAPS, DPOFlat
from sb3_dipper.common.hierarchical_policy import SACPolicyLowLevel
from sb3_dipper.common.planning import SubgoalGraph
from sb3_dipper.common.preferences import start_gaps
from sb3_dipper.common.subgoals import SubgoalSpace
from sb3_dipper.common.trajectories import TrajectoryBuffer
from sb3_dipper.dipper import DEFAULT_SWITCH_KWARGS, DIPPERPolicy
from tests.conftest import SHORT_EPISODES, any_tiny_model, saved_in_old_form, short_maze, tiny_model
from tests.test_preferences import OBS_SPACE, add_trajectory
from tests.test_save_load import rollout_actions
from zoo_scripts.configs import trained_run
from zoo_scripts.research import planner_share

REPO = Path(__file__).resolve().parent.parent

SPACE = SubgoalSpace(low=np.zeros(2), high=np.full(2, 10.0), threshold=0.5)


@pytest.fixture
def graph() -> SubgoalGraph:
    buffer = TrajectoryBuffer(capacity=10, max_length=4, observation_space=OBS_SPACE, action_dim=2)
    # Two trajectories that never meet end to end: (0.5,0.5) -> ... -> (3.5,0.5) and (3.5,0.5) -> ... -> (3.5,3.5).
    add_trajectory_from(buffer, (0.5, 0.5), [(1.5, 0.5), (2.5, 0.5), (3.5, 0.5)])
    add_trajectory_from(buffer, (3.5, 0.5), [(3.5, 1.5), (3.5, 2.5), (3.5, 3.5)])
    graph = SubgoalGraph(SPACE, resolution=1.0)
    graph.rebuild(buffer)
    return graph


def add_trajectory_from(buffer: TrajectoryBuffer, start, path) -> None:
    """A trajectory whose first observation is at ``start`` (add_trajectory starts at the origin)."""
    shifted = [(x - start[0], y - start[1]) for x, y in path]
    before = buffer.pos
    add_trajectory(buffer, shifted)
    buffer.observations["achieved_goal"][before, : len(path)] += np.array(start, dtype=np.float32)
    buffer.next_achieved_goals[before, : len(path)] += np.array(start, dtype=np.float32)


def test_voxels_and_edges(graph):
    assert len(graph) == 7
    assert graph.voxel_ids(np.array([[0.5, 0.5], [1.2, 0.1], [9.9, 9.9], [12.0, -3.0]])).tolist() == [0, 10, 99, 90]
    assert len(graph.edges) == 6


def test_shortest_paths_stitch_trajectories(graph):
    goal = graph._index[int(graph.voxel_ids(np.array([[3.5, 3.5]]))[0])]
    start = graph._index[int(graph.voxel_ids(np.array([[0.5, 0.5]]))[0])]
    assert graph.distances_to(goal)[start] == 6.0


def assert_plan(plan, waypoints, planned):
    np.testing.assert_allclose(plan.waypoints, waypoints)
    assert plan.planned.dtype == bool and plan.planned.tolist() == planned


def test_waypoints_walk_the_path(graph):
    start, goal = np.array([[0.4, 0.6]]), np.array([[3.5, 3.4]])
    assert_plan(graph.plan(start, goal, lookahead=1), [[1.5, 0.5]], [True])
    assert_plan(graph.plan(start, goal, lookahead=4), [[3.5, 1.5]], [True])
    # The goal within the lookahead: the waypoint is the goal itself (not its voxel's mean), and it is planned.
    assert_plan(graph.plan(np.array([[3.5, 2.5]]), goal, lookahead=3), goal, [True])


def test_unvisited_goal_voxels_plan_to_the_nearest_visited_voxel(graph):
    goal = np.array([[4.6, 3.5]])  # one voxel right of (3.5, 3.5)
    assert_plan(graph.plan(np.array([[3.5, 2.5]]), goal, lookahead=1), [[3.5, 3.5]], [True])
    far_goal = np.array([[9.0, 9.0]])
    assert_plan(graph.plan(np.array([[3.5, 2.5]]), far_goal, lookahead=1), far_goal, [False])


def test_without_a_known_path_nothing_is_planned(graph):
    # Edges are directed: nothing leads back from (3.5, 3.5) to the start.
    goal = np.array([[0.5, 0.5]])
    assert_plan(graph.plan(np.array([[3.5, 3.5]]), goal, lookahead=1), goal, [False])
    empty = SubgoalGraph(SPACE, resolution=1.0)
    assert_plan(empty.plan(np.array([[1.0, 1.0]]), goal, lookahead=1), goal, [False])
    # Already in the goal's own voxel: nothing to plan.
    assert_plan(graph.plan(np.array([[3.4, 3.6]]), np.array([[3.5, 3.5]]), lookahead=1), [[3.5, 3.5]], [False])
    # An unknown start voxel.
    assert_plan(graph.plan(np.array([[8.5, 8.5]]), np.array([[3.5, 3.5]]), lookahead=1), [[3.5, 3.5]], [False])


def test_plan_rows_are_independent(graph):
    achieved = np.array([[0.4, 0.6], [3.5, 3.5], [3.5, 2.5]])
    goals = np.array([[3.5, 3.4], [0.5, 0.5], [3.5, 3.4]], dtype=np.float64)
    assert_plan(graph.plan(achieved, goals, lookahead=1), [[1.5, 0.5], [0.5, 0.5], [3.5, 3.4]], [True, False, True])


def test_resolution_must_be_positive():
    with pytest.raises(ValueError, match="resolution must be positive"):
        SubgoalGraph(SPACE, resolution=0.0)


# ---------------------------------------------------------------------------------------------------- who proposes


def one_room_maze(seed: int = 0):
    """The short maze with the goal in the start room, where 20-step episodes reach it and the graph learns paths."""
    env_kwargs = {**SHORT_EPISODES, "goal_room": "bottom_left"}
    return make_vec_env("sb3_dipper:PointMazeFourRooms-v0", n_envs=1, seed=seed, env_kwargs=env_kwargs)


def grid_graph(model: DIPPER) -> None:
    """Give the model's graph every voxel of its subgoal space, each joined both ways to its four neighbours (the walls
    ignored), so that it knows a path from everywhere to everywhere."""
    graph = model.planner.graph
    cells = np.stack(np.meshgrid(*(np.arange(n) for n in graph.grid_shape), indexing="ij"), -1).reshape(-1, 2)
    points = (graph.subgoal_space.low + (cells + 0.5) * graph.resolution).astype(np.float32)
    ids = graph.voxel_ids(points)
    graph.set_nodes(ids, points)
    step = {tuple(cell): voxel for cell, voxel in zip(cells.tolist(), ids.tolist(), strict=True)}
    edges = [
        (voxel, step[(a + da, b + db)])
        for (a, b), voxel in step.items()
        for da, db in ((0, 1), (1, 0), (0, -1), (-1, 0))
        if (a + da, b + db) in step
    ]
    graph.set_edges(np.array(edges))


def test_planner_decisions_are_marked_and_their_share_logged(tmp_path):
    model = tiny_model(DIPPER, one_room_maze(), planner_kwargs=dict(mode="subgoal", lookahead=2))
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(400, log_interval=1)
    assert len(model.planner.graph) > 0
    shares = pd.read_csv(tmp_path / "progress.csv")["rollout/planned_share"].dropna()
    # Short episodes seldom know a path to their goal: the planner plans a few rows, the policy the rest.
    assert len(shares) > 0 and ((shares >= 0) & (shares < 1)).all() and shares.max() > 0
    maze_env = one_room_maze()

    observation = maze_env.reset()
    actions = model._high_level_actions(observation, deterministic=True)
    plan = model.planner.plan(observation, model.low_normalizer, training=True)
    np.testing.assert_array_equal(model.last_planned, plan.planned)
    np.testing.assert_array_equal(actions[plan.planned], model.subgoal_space.to_unit(plan.waypoints[plan.planned]))
    model.planner.graph = None  # the planner off: the policy proposes every subgoal
    model._high_level_actions(observation, deterministic=True)
    assert model.last_planned.shape == (1,) and not model.last_planned.any()


def test_plan_in_predict_false_plans_in_training_only(tmp_path):
    models = {}
    for in_predict in (True, False):
        planner_kwargs = dict(mode="subgoal", lookahead=2, in_predict=in_predict)
        model = tiny_model(DIPPER, one_room_maze(), planner_kwargs=planner_kwargs)
        model.set_logger(configure(str(tmp_path / str(in_predict)), ["csv"]))
        model.learn(400, log_interval=1)
        models[in_predict] = model
    # Training is the same run: the planner steered some training proposals either way.
    assert (pd.read_csv(tmp_path / "False" / "progress.csv")["rollout/planned_share"].dropna() > 0).any()
    for trained, policy_only in zip(models[True].policy.parameters(), models[False].policy.parameters(), strict=True):
        assert th.equal(trained, policy_only)

    model = models[False]
    grid_graph(model)  # a path from everywhere: predict would plan every row if it planned
    observation = short_maze(seed=3).reset()
    actions, _ = model.predict(observation, deterministic=True)
    assert not model.last_planned.any()  # the preference-trained policy proposed the subgoal
    model.planner.in_predict = True
    model.predict(observation, deterministic=True)
    assert model.last_planned.all()
    model.planner.in_predict = False
    # Nothing of the planner is needed to act, so the model exports; the exported policy acts as predict does.
    exported_actions, _ = model.export_policy().predict(observation, deterministic=True)
    np.testing.assert_array_equal(exported_actions, actions)
    model.save(tmp_path / "model")
    assert DIPPER.load(tmp_path / "model").planner.in_predict is False


@pytest.mark.parametrize("mode", ["off", "waypoint"])
def test_plan_in_predict_false_needs_the_subgoal_planner(maze_env, mode):
    with pytest.raises(ValueError, match="in_predict=False needs mode='subgoal'"):
        tiny_model(DIPPER, maze_env, planner_kwargs=dict(mode=mode, in_predict=False))


@pytest.mark.tools
def test_planner_share_script_evaluates_the_model_and_its_checkpoints_four_ways_or_three_without_a_planner(tmp_path):
    run = tmp_path / "dipper" / "PointMazeFourRooms-v0_1"
    maze_env = make_vec_env("sb3_dipper:PointMazeFourRooms-v0", n_envs=1, seed=0)  # the zoo entry's 200-step episodes
    model = tiny_model(DIPPER, maze_env, planner_kwargs=dict(mode="subgoal", lookahead=2))
    model.learn(1000)  # the graph is built after 4 episodes
    grid_graph(model)  # a path from everywhere, so that the planner plans (on 1,000 steps it seldom knows one)
    model.save(run / "PointMazeFourRooms-v0.zip")
    # Checkpoints as rl-zoo3's CheckpointCallback names them (benchmark.py --save-freq), out of order on disk.
    model.save(run / "rl_model_1000_steps.zip")
    model.num_timesteps = 800
    model.save(run / "rl_model_800_steps.zip")
    command = [sys.executable, str(REPO / "zoo_scripts" / "research" / "planner_share.py"), str(run), "--episodes", "1"]
    command += ["--csv", str(tmp_path / "share.csv")]
    done = subprocess.run([*command, "--checkpoints"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads((run / "planner_share.json").read_text())
    assert list(report) == ["as_trained", "untrained_policy", "policy_alone", "lower_level_alone"]
    rows = pd.read_csv(tmp_path / "share.csv")
    assert rows["steps"].tolist() == [800] * 4 + [1000] * 4 + [1000] * 4  # the checkpoints in order, then the final model
    rows = rows.iloc[-4:]
    assert rows["case"].tolist() == list(report) and rows["success"].tolist() == [c["success"] for c in report.values()]
    assert all(0 <= case["success"] <= 1 and 0 <= case["planned_share"] <= 1 for case in report.values())
    assert report["as_trained"]["planned_share"] > 0
    assert report["policy_alone"]["planned_share"] == report["lower_level_alone"]["planned_share"] == 0

    # Without the planner (the paper's DIPPER, DIPPER-No-V) the model as trained is its policy alone: three cases.
    tiny_model(DIPPER, maze_env).save(run / "PointMazeFourRooms-v0.zip")
    done = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads((run / "planner_share.json").read_text())
    assert list(report) == ["as_trained", "untrained_policy", "lower_level_alone"]
    assert all(case["planned_share"] == 0 for case in report.values())
    # How far the subgoals decided lie from the goal and from where the agent was: the goal's own are at the goal.
    assert report["lower_level_alone"]["subgoal_to_goal"] == pytest.approx(0.0, abs=1e-5)
    assert report["lower_level_alone"]["subgoal_to_achieved"] > 0.1 and report["as_trained"]["subgoal_to_goal"] > 0.1
    assert pd.read_csv(tmp_path / "share.csv")["case"].tolist() == list(report)


@pytest.mark.tools
def test_planner_share_sampled_cases_sample_the_levels_as_training_collects(tmp_path, monkeypatch):
    """``--sampled``: both levels sample (``sampled``), or the higher level samples and the lower is greedy."""
    run = tmp_path / "dipper" / "PointMazeFourRooms-v0_1"
    maze_env = make_vec_env("sb3_dipper:PointMazeFourRooms-v0", n_envs=1, seed=0)  # the zoo entry's 200-step episodes
    tiny_model(DIPPER, maze_env).save(run / "PointMazeFourRooms-v0.zip")
    calls = {"higher": [], "lower": []}
    high_level_actions, lower_actions = DIPPER._high_level_actions, SACPolicyLowLevel.act

    def spy_higher(self, observation, deterministic):
        calls["higher"].append(deterministic)
        return high_level_actions(self, observation, deterministic)

    def spy_lower(self, low_obs, deterministic, normalized=True):
        calls["lower"].append(deterministic)
        return lower_actions(self, low_obs, deterministic, normalized)

    monkeypatch.setattr(DIPPER, "_high_level_actions", spy_higher)
    monkeypatch.setattr(SACPolicyLowLevel, "act", spy_lower)
    expected = {
        "as_trained": (True, True),
        "untrained_policy": (True, True),
        "lower_level_alone": (None, True),
        "sampled": (False, False),
        "greedy_lower": (False, True),
    }
    _, report = planner_share.measure(run, "dipper", "PointMazeFourRooms-v0", n_episodes=1, sampled=True)
    assert list(report) == list(expected)
    for case, (higher, lower) in expected.items():
        calls["higher"].clear()
        calls["lower"].clear()
        model, env = trained_run(run, "dipper", "PointMazeFourRooms-v0", seed=0)
        planner_share.evaluate(model, env, 1, **planner_share.case_settings(case))
        assert set(calls["higher"]) == (set() if higher is None else {higher}), case
        assert set(calls["lower"]) == {lower}, case


@pytest.mark.tools
def test_planner_share_measures_a_baseline_three_ways_and_refuses_a_scripted_lower_level(tmp_path):
    """A HIER has no planner: as trained, with its higher policy untrained, and its lower level driven by the goal
    (which the goal case hands to the lower level as its subgoal); RAPS has no learned lower level to measure."""
    run = tmp_path / "hier" / "PointMazeFourRooms-v0_1"
    maze_env = make_vec_env("sb3_dipper:PointMazeFourRooms-v0", n_envs=1, seed=0)
    tiny_model(HIER, maze_env).save(run / "PointMazeFourRooms-v0.zip")
    _, report = planner_share.measure(run, "hier", "PointMazeFourRooms-v0", n_episodes=1)
    assert list(report) == ["as_trained", "untrained_policy", "lower_level_alone"]
    assert all(case["planned_share"] == 0 for case in report.values())
    model, env = trained_run(run, "hier", "PointMazeFourRooms-v0", seed=0)
    observation = env.reset()
    subgoals = model.subgoal_space.to_world(model._subgoal_actions(observation["desired_goal"]))
    np.testing.assert_allclose(subgoals, model.subgoal_space.project(observation["desired_goal"]), atol=1e-5)
    raps_run = tmp_path / "raps" / "PointMazeFourRooms-v0_1"
    any_tiny_model(RAPS, maze_env).save(raps_run / "PointMazeFourRooms-v0.zip")
    with pytest.raises(ValueError, match="is a RAPS, not a hierarchical model with a learned lower level"):
        planner_share.measure(raps_run, "raps", "PointMazeFourRooms-v0", n_episodes=1)


def test_planner_share_refuses_a_folder_that_is_not_there_before_measuring_any(tmp_path, monkeypatch, capsys):
    run = tmp_path / "dipper" / "PointMazeFourRooms-v0_1"
    run.mkdir(parents=True)
    monkeypatch.setattr(sys, "argv", ["planner_share.py", str(run), str(tmp_path / "typo_1"), "--checkpoints"])
    with pytest.raises(SystemExit) as exited:
        planner_share.main()
    assert exited.value.code == 2
    assert f"{tmp_path / 'typo_1'}: no such run folder" in capsys.readouterr().err


# ------------------------------------------------------------------------------- who acts where the planner did not


def planning_model(normalize: bool) -> DIPPER:
    """A DIPPER that plans subgoals on the short four-room maze, with ``VecNormalize`` statistics that are not the
    identity when ``normalize`` (so a goal that went through the normaliser's round trip differs from the observation's)."""
    env = short_maze()
    if normalize:
        env = VecNormalize(env, norm_obs=True, norm_reward=False)
        env.reset()
        for _ in range(200):  # ten episodes: ten goals, so the goal's statistics are not a single point
            env.step(np.array([env.action_space.sample()]))
        env.training = False  # the statistics stay those the model copies
    model = tiny_model(DIPPER, env, planner_kwargs=dict(mode="subgoal", lookahead=2), random_subgoal_prob=0.0)
    model._refresh_low_normalizer()
    return model


def observation_at(model: DIPPER, achieved: list[float], goal: list[float], dtype) -> dict:
    """A (normalised, where the model normalises) observation whose achieved and desired goals are the given points."""
    observation = {key: np.array(value, dtype=np.float64) for key, value in model.env.reset().items()}
    if model._vec_normalize_env is not None:
        observation = model._vec_normalize_env.get_original_obs()
    observation["achieved_goal"][:] = achieved
    observation["desired_goal"][:] = goal
    if model._vec_normalize_env is not None:
        observation = model._vec_normalize_env.normalize_obs(observation)
    return {key: value.astype(dtype) for key, value in observation.items()}


def known_path(model: DIPPER, points: list[list[float]]) -> None:
    """The model's graph: a chain of edges through ``points`` (world coordinates)."""
    graph = model.planner.graph
    points_array = np.array(points, dtype=np.float32)
    ids = graph.voxel_ids(points_array)
    graph.set_nodes(ids, points_array)
    graph.set_edges(np.stack([ids[:-1], ids[1:]], axis=1))


def proposals(model: DIPPER, observation: dict, training: bool) -> np.ndarray:
    """The higher-level actions as training collects them (sampled, with the graph) or as ``predict`` decides them,
    each from the same torch seed, so the policy's own sample is the same in every call."""
    th.manual_seed(7)
    if training:
        return model._collecting_high_level_actions(observation)
    return model._high_level_actions(observation, deterministic=True)


def policy_proposals(model: DIPPER, observation: dict, training: bool) -> np.ndarray:
    th.manual_seed(7)
    actions, _ = model.policy.predict(observation, deterministic=not training)
    return np.asarray(actions, dtype=np.float32).reshape(1, -1)


CASES_WITHOUT_A_PLAN = {
    # no edge at all
    "empty graph": ([], [-2.5, -2.5], [2.5, 2.5]),
    # the agent is already in the goal's voxel, which the graph knows
    "goal's own voxel": ([[-2.5, -2.5], [2.5, 2.5]], [2.45, 2.55], [2.5, 2.5]),
    # the goal is known, but nothing leads from here to it
    "no path": ([[-2.5, -2.5], [2.5, 2.5]], [2.5, 2.5], [-2.5, -2.5]),
}


@pytest.mark.parametrize("training", [True, False], ids=["training", "predict"])
@pytest.mark.parametrize("normalize", [False, True], ids=["raw", "VecNormalize"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("case", list(CASES_WITHOUT_A_PLAN))
def test_where_the_planner_did_not_plan_the_policy_acts(case, dtype, normalize, training):
    model = planning_model(normalize)
    path, achieved, goal = CASES_WITHOUT_A_PLAN[case]
    if path:
        known_path(model, path)
    observation = observation_at(model, achieved, goal, dtype)
    actions = proposals(model, observation, training)
    assert model.last_planned.tolist() == [False]
    np.testing.assert_array_equal(actions, policy_proposals(model, observation, training))


@pytest.mark.parametrize("training", [True, False], ids=["training", "predict"])
@pytest.mark.parametrize("normalize", [False, True], ids=["raw", "VecNormalize"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_a_known_path_is_planned_to_its_waypoint_and_to_the_goal_within_the_lookahead(dtype, normalize, training):
    model = planning_model(normalize)
    known_path(model, [[-2.5, -2.5], [-1.5, -2.5], [-0.5, -2.5], [0.5, -2.5]])
    # Three options away with a lookahead of 2: the waypoint two voxels along.
    actions = proposals(model, observation_at(model, [-2.5, -2.5], [0.5, -2.5], dtype), training)
    assert model.last_planned.tolist() == [True]
    np.testing.assert_allclose(model.subgoal_space.to_world(actions), [[-0.5, -2.5]], atol=1e-5)
    # One option away: the goal itself is the planned subgoal.
    actions = proposals(model, observation_at(model, [-0.5, -2.5], [0.45, -2.4], dtype), training)
    assert model.last_planned.tolist() == [True]
    np.testing.assert_allclose(model.subgoal_space.to_world(actions), [[0.45, -2.4]], atol=1e-5)


def test_planning_off_and_an_empty_graph_act_identically():
    env = short_maze(n_envs=2)
    planning = tiny_model(DIPPER, env, planner_kwargs=dict(mode="subgoal"))
    off = tiny_model(DIPPER, env)
    off.policy.load_state_dict(planning.policy.state_dict())
    off.lower.policy.load_state_dict(planning.lower.policy.state_dict())
    assert len(planning.planner.graph) == 0 and off.planner.graph is None
    observation, state, episode_start = env.reset(), None, np.ones(2, dtype=bool)
    for _ in range(20):
        action, state_planning = planning.predict(observation, state, episode_start, deterministic=True)
        action_off, state = off.predict(observation, state, episode_start, deterministic=True)
        np.testing.assert_array_equal(action, action_off)
        np.testing.assert_array_equal(state_planning[0], state[0])
        assert not planning.last_planned.any()
        observation, _, dones, _ = env.step(action)
        episode_start = dones


def test_random_subgoals_are_not_counted_as_planned(tmp_path):
    model = tiny_model(DIPPER, short_maze(), planner_kwargs=dict(mode="subgoal", lookahead=2), random_subgoal_prob=1.0)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(400, log_interval=1)
    assert len(model.planner.graph) > 0
    observation = model.env.reset()
    model._collecting_high_level_actions(observation)
    planned_by_graph = model.last_planned.copy()
    model._training_high_level_actions(observation)
    assert model.last_random_subgoals.all() and not model.last_planned.any()
    shares = pd.read_csv(tmp_path / "progress.csv")["rollout/planned_share"].dropna()
    assert len(shares) > 0 and (shares == 0).all()
    # The graph itself did plan some rows: only the swaps hid them.
    assert planned_by_graph.shape == (1,)


def test_a_trained_higher_policy_acts_differently_from_an_untrained_one(maze_env):
    """On the fast maze, with the planner steering training only, the evaluation's subgoals are the policy's: resetting
    the higher policy to untrained weights changes them (before the planner flag was returned by the planner, every row
    counted as planned and the two evaluations were the same)."""
    model = tiny_model(DIPPER, maze_env, planner_kwargs=dict(mode="subgoal", lookahead=2, in_predict=False))
    model.learn(600)
    assert len(model.preferences) > 0 and len(model.planner.graph) > 0
    trained = evaluation_subgoals(model)
    assert not model.last_planned.any()
    planner_share.reset_higher_policy(model, seed=1)
    untrained = evaluation_subgoals(model)
    assert trained.shape == untrained.shape and not np.allclose(trained, untrained)


def evaluation_subgoals(model: DIPPER) -> np.ndarray:
    """The subgoals of one deterministic 20-step episode from a fixed start, as ``predict`` carries them."""
    env = short_maze(seed=5)
    observation, state, episode_start, subgoals = env.reset(), None, np.ones(1, dtype=bool), []
    for _ in range(20):
        action, state = model.predict(observation, state, episode_start, deterministic=True)
        subgoals.append(state[0].copy())
        observation, _, episode_start, _ = env.step(action)
    return np.concatenate(subgoals)


def test_dipper_logs_what_its_new_labels_carry(tmp_path):
    logs = {}
    for source in ("primitive", "progress"):
        model = tiny_model(DIPPER, short_maze(), preference_source=source)
        model.set_logger(configure(str(tmp_path / source), ["csv"]))
        model.learn(400, log_interval=1)
        logs[source] = log = pd.read_csv(tmp_path / source / "progress.csv")
        for key in ("train/high_new_tie_share", "train/high_label_progress_agreement", "train/high_new_pair_accuracy"):
            values = log[key].dropna()
            assert len(values) > 0 and ((values >= 0) & (values <= 1)).all(), (source, key)
        assert (log["train/high_new_logp_preferred"].dropna() < 10).all() and log["train/high_new_logp_rejected"].notna().any()
    # Measured: a third of the scripted labels tie, 0.15 with progress answering them (a pair still ties where both
    # trajectories end at the same point, as one trajectory drawn twice does early on).
    ties = {source: log["train/high_new_tie_share"].mean() for source, log in logs.items()}
    assert ties["primitive"] > 0.2 and ties["progress"] < ties["primitive"] / 2
    agreement = {source: log["train/high_label_progress_agreement"].mean() for source, log in logs.items()}
    assert agreement["progress"] > agreement["primitive"]


def test_an_averaged_reference_starts_every_pair_at_a_tie():
    # Where the averaged actor equals the trained one every logit is 0 (lambda = 0), so the DPO loss is ln 2 whatever
    # the labels; with the uniform reference it is not.
    losses = {}
    for reference in ("uniform", "averaged"):
        model = tiny_model(
            DIPPER,
            short_maze(),
            switch_kwargs=dict(reference=reference),
            high_gradient_steps=1,
            value_reg_coef=0.0,
            policy_kwargs=dict(net_arch=[16], acting_tau=0.05),
        )
        model.learn(300)
        assert len(model.preferences) > 0
        if model.policy.averaged_actor is not None:
            model.policy.averaged_actor.load_state_dict(model.policy.actor.state_dict())
        model._train_high_level()
        losses[reference] = model.logger.name_to_value["train/high_dpo_loss"]
    assert losses["averaged"] == pytest.approx(math.log(2), abs=1e-5)
    assert losses["uniform"] != pytest.approx(math.log(2), abs=1e-3)
    with pytest.raises(ValueError, match="acting_tau below 1"):
        tiny_model(DIPPER, short_maze(), switch_kwargs=dict(reference="averaged"))


def test_a_log_std_floor_bounds_the_log_density_of_stored_subgoals(tmp_path):
    """log p(u) of the squashed Gaussian at the floor, by hand: the actor's own log-std (-10) is raised to -1."""
    densities = {}
    for floor in (-20.0, -1.0):
        model = tiny_model(DIPPER, short_maze(), policy_kwargs=dict(net_arch=[16], log_std_min=floor))
        actor = model.policy.actor
        with th.no_grad():
            for head, bias in ((actor.mu, 0.0), (actor.log_std, -10.0)):
                head.weight.zero_()
                head.bias.fill_(bias)
        observation, _ = model.policy.obs_to_tensor(short_maze().reset())
        action = th.full((1, 2), math.tanh(0.5))
        densities[floor] = model.policy.log_prob(observation, action).item()
        std = math.exp(max(floor, -10.0))
        by_hand = 2 * (
            -0.5 * (0.5 / std) ** 2 - math.log(std) - 0.5 * math.log(2 * math.pi) - math.log(1 - math.tanh(0.5) ** 2)
        )
        assert densities[floor] == pytest.approx(by_hand, rel=1e-4)
    assert densities[-20.0] < -1e7 < densities[-1.0]
    # It is saved with the model and checked.
    model.save(tmp_path / "floored.zip")
    assert DIPPER.load(tmp_path / "floored.zip").policy.actor.log_std_min == -1.0
    with pytest.raises(ValueError, match=r"log_std_min must be a number in \[-20, 2\)"):
        tiny_model(DIPPER, short_maze(), policy_kwargs=dict(net_arch=[16], log_std_min=2.0))


@pytest.mark.parametrize("normalize", [False, True])
def test_a_goal_anchored_policy_starts_at_the_goal_and_learns_offsets_from_it(normalize, tmp_path):
    env = short_maze(n_envs=2)
    if normalize:  # the anchor follows the statistics, which training moves
        env = VecNormalize(env, norm_obs=True, norm_reward=False)
    model = tiny_model(DIPPER, env, policy_kwargs=dict(net_arch=[16], goal_anchored=True))

    def proposals(acting, observation):
        acting._refresh_low_normalizer()
        return acting.subgoal_space.to_world(acting._high_level_actions(observation, deterministic=True))

    def observation_and_goals():
        observation = env.reset()
        return observation, env.get_original_obs()["desired_goal"] if normalize else observation["desired_goal"]

    observation, goals = observation_and_goals()
    np.testing.assert_allclose(proposals(model, observation), goals, atol=1e-3 * 7.0)  # the anchor's epsilon, 7 m box
    model.learn(200)
    if normalize:
        env.training = False
    observation, goals = observation_and_goals()
    trained = proposals(model, observation)
    assert np.abs(trained - goals).max() > 1e-2  # the preference loss moved the mean off the goal
    model.save(tmp_path / "trained.zip")
    loaded = DIPPER.load(tmp_path / "trained.zip")  # the anchor's map is saved with the policy
    np.testing.assert_allclose(proposals(loaded, observation), trained, atol=1e-5)
    planner_share.reset_higher_policy(model, seed=1)  # the control "higher policy untrained": the goal again
    np.testing.assert_allclose(proposals(model, observation), goals, atol=1e-3 * 7.0)


def test_the_anchor_leash_holds_a_goal_anchored_policy_nearer_the_goal(tmp_path):
    """With ``anchor_coef`` the squared offset from the goal's action joins the loss: the same run (seed, pairs) ends
    with its proposals nearer the goal than without it, and the mean offset is logged."""
    env = short_maze(n_envs=2)

    def offsets(anchor_coef):
        model = tiny_model(
            DIPPER, env, policy_kwargs=dict(net_arch=[16], goal_anchored=True), switch_kwargs=dict(anchor_coef=anchor_coef)
        )
        model.set_logger(configure(str(tmp_path / str(anchor_coef)), ["csv"]))
        model.learn(200)
        with th.no_grad():
            observation = obs_as_tensor(env.reset(), model.device)
            return model.policy.actor.offset_from_the_anchor(observation).abs().max().item()

    free = offsets(0.0)
    leashed = offsets(100.0)
    assert leashed < free / 2
    logged = pd.read_csv(tmp_path / "100.0" / "progress.csv")["train/high_anchor_offset"].dropna()
    assert len(logged) and (logged >= 0).all()
    assert "train/high_anchor_offset" not in pd.read_csv(tmp_path / "0.0" / "progress.csv")
    with pytest.raises(ValueError, match=r"switch_kwargs\['anchor_coef'\] pulls a goal-anchored policy's subgoals"):
        tiny_model(DIPPER, env, switch_kwargs=dict(anchor_coef=1.0))


def test_goal_anchoring_needs_a_goal_and_a_subgoal_box():
    with pytest.raises(ValueError, match="goal_anchored=True anchors the higher level's subgoals at the observed goal"):
        DIPPERPolicy(spaces.Box(-1, 1, (3,)), spaces.Box(-1, 1, (2,)), lambda _: 1e-3, goal_anchored=True)
    with pytest.raises(ValueError, match="DPO-FLAT's actions are primitive actions"):
        DPOFlat("MultiInputPolicy", short_maze(), segment_length=5, policy_kwargs=dict(goal_anchored=True))


@pytest.mark.parametrize("normalize", [False, True])
def test_goal_subgoals_execute_the_envs_goal_in_training_only(normalize):
    env = short_maze(n_envs=2)
    if normalize:
        env = VecNormalize(env, norm_obs=True, norm_reward=False)
    model = tiny_model(
        DIPPER,
        env,
        switch_kwargs=dict(goal_subgoal_prob=1.0),
        random_subgoal_prob=0.0,
        planner_kwargs=dict(mode="subgoal"),
    )
    model.learn(120)
    if normalize:  # the statistics stay those the model copies
        env.training = False
        model._refresh_low_normalizer()
    observation = env.reset()
    goals = env.get_original_obs()["desired_goal"] if normalize else observation["desired_goal"]
    training = model._training_high_level_actions(observation)
    np.testing.assert_allclose(model.subgoal_space.to_world(training), goals, atol=1e-4)
    assert not model.last_planned.any() and not model.last_random_subgoals.any()
    # predict (evaluation) proposes with the policy, never the goal.
    predicted = model._high_level_actions(observation, deterministic=True)
    assert not np.allclose(model.subgoal_space.to_world(predicted), goals, atol=1e-2)


def test_goal_episodes_are_whole_control_episodes_in_training_only():
    model = tiny_model(DIPPER, short_maze(n_envs=4), switch_kwargs=dict(goal_episode_prob=0.5), random_subgoal_prob=0.5)
    decisions = []  # per decision and env: (whether its episode had begun, driven by the goal, action, goal action)
    collect = model._training_high_level_actions

    def recorded(observation):
        begun = [len(steps) > 0 for steps in model.trajectory_buffer._open]
        actions = collect(observation)
        if model.num_timesteps >= model.learning_starts:
            assert not (model.last_random_subgoals & model.goal_episodes).any()  # the control is not explored
            goal_actions = model._subgoal_actions(observation["desired_goal"])
            decisions.append((np.array(begun), model.goal_episodes.copy(), actions.copy(), goal_actions))
        return actions

    model._training_high_level_actions = recorded
    model.learn(600)
    assert len(decisions) > 10
    for (_, before, _, _), (begun, now, _, _) in itertools.pairwise(decisions):
        np.testing.assert_array_equal(now[begun], before[begun])  # drawn once per episode
    flags = np.concatenate([now for _, now, _, _ in decisions])
    assert 0.2 < flags.mean() < 0.8
    for _, now, actions, goal_actions in decisions:
        np.testing.assert_allclose(actions[now], goal_actions[now], atol=1e-6)
        assert not np.isclose(actions[~now], goal_actions[~now], atol=1e-3).all(axis=1).any()
    stored = model.trajectory_buffer.goal_driven[: len(model.trajectory_buffer)]  # the buffer knows who drove
    assert stored.any() and not stored.all()
    finished = [model._option_metrics[f"{driver}_episode_success"] for driver in ("goal", "policy")]
    assert all(len(successes) > 0 and set(successes) <= {0.0, 1.0} for successes in finished)
    logged = model._option_metrics["goal_episode_share"]  # rollout/goal_episode_share averages these
    assert np.mean(logged) == pytest.approx(flags[-len(logged) :].mean())
    # predict proposes with the policy; the switch is a training-only teacher.
    observation = model.env.reset()
    predicted = model._high_level_actions(observation, deterministic=True)
    assert not np.isclose(predicted, model._subgoal_actions(observation["desired_goal"]), atol=1e-3).all(axis=1).any()


def test_matched_control_pairs_pit_the_policy_against_the_control_from_near_starts(tmp_path):
    switches = dict(goal_episode_prob=0.5, matched_control_prob=1.0)
    model = tiny_model(DIPPER, short_maze(n_envs=2), switch_kwargs=switches)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(250, log_interval=1)
    assert pd.read_csv(tmp_path / "progress.csv")["train/high_new_start_gap"].notna().any()
    sampler, buffer = model.preference_pipeline.sampler, model.trajectory_buffer
    matched = sampler.sample(buffer, 50, np.random.default_rng(0))
    goal_actions = model._subgoal_actions(matched.observations["desired_goal"][1][matched.mask[1]])
    np.testing.assert_allclose(matched.actions[1][matched.mask[1]], goal_actions, atol=1e-5)  # tau^2: the control's
    sampler.matched_control_prob = 0.0
    drawn = sampler.sample(buffer, 50, np.random.default_rng(0))
    assert start_gaps(matched).mean() < start_gaps(drawn).mean()


def test_goal_episodes_log_their_success_apart_from_the_policys():
    model = tiny_model(DIPPER, short_maze(n_envs=3), switch_kwargs=dict(goal_episode_prob=0.5))
    model._setup_learn(10)
    model.goal_episodes = np.array([True, False, True])
    infos = [{"is_success": 1.0}, {"is_success": 0.0}, {"is_success": 1.0}]
    model._record_success_by_driver(np.array([1, 1, 0]), infos)  # the third env's episode goes on
    assert list(model._option_metrics["goal_episode_success"]) == [1.0]
    assert list(model._option_metrics["policy_episode_success"]) == [0.0]


def test_goal_episodes_are_off_by_default_and_draw_nothing():
    model = tiny_model(DIPPER, short_maze(n_envs=2))
    state = model._rng.bit_generator.state
    model._draw_goal_episodes(np.ones(2, dtype=bool))
    assert model.goal_episodes is None and model._rng.bit_generator.state == state
    assert "goal_episode_share" not in model._option_metric_keys()


def test_a_run_is_measured_on_the_env_kwargs_it_trained_with(tmp_path):
    from collections import OrderedDict

    import yaml

    from zoo_scripts.configs import run_env_kwargs

    (tmp_path / "Env-v0").mkdir()
    # rl-zoo3 saves the hyperparameters as a Python-tagged OrderedDict.
    saved = OrderedDict([("batch_size", 256), ("env_kwargs", {"max_episode_steps": 50})])
    (tmp_path / "Env-v0" / "config.yml").write_text(yaml.dump(saved))
    assert run_env_kwargs(tmp_path, "Env-v0") == {"max_episode_steps": 50}
    assert run_env_kwargs(tmp_path, "Other-v0") is None
    (tmp_path / "Env-v0" / "config.yml").write_text("!!python/object/apply:os.system ['echo unsafe']\n")
    with pytest.raises(ValueError, match="not the configuration rl-zoo3 saves"):
        run_env_kwargs(tmp_path, "Env-v0")


# ------------------------------------------------------------------------------- planner_kwargs, and the form before it

OLD_FORM = dict(planning="subgoal", planning_lookahead=2, plan_in_predict=False, planning_value_threshold=-12.0)
NEW_FORM = dict(mode="subgoal", lookahead=2, in_predict=False, value_threshold=-12.0)


def test_the_five_planning_parameters_still_work_and_warn_naming_planner_kwargs(tmp_path):
    message = (
        "DIPPER's planning, plan_in_predict, planning_lookahead, planning_value_threshold are deprecated: pass "
        "planner_kwargs={'mode': 'subgoal', 'in_predict': False, 'lookahead': 2, 'value_threshold': -12.0} instead"
    )
    with pytest.warns(DeprecationWarning, match=re.escape(message)):
        old = tiny_model(DIPPER, one_room_maze(), **OLD_FORM)
    # The same planner and the same run: the same graph, logs and actions (each model built and trained in turn, as
    # building one seeds torch's global generator, which training draws from).
    old.set_logger(configure(str(tmp_path / "old"), ["csv"]))
    old.learn(400, log_interval=1)
    new = tiny_model(DIPPER, one_room_maze(), planner_kwargs=NEW_FORM)
    new.set_logger(configure(str(tmp_path / "new"), ["csv"]))
    new.learn(400, log_interval=1)
    assert old.planner_kwargs == new.planner_kwargs == NEW_FORM
    np.testing.assert_array_equal(old.planner.graph.edges, new.planner.graph.edges)
    logs = [pd.read_csv(tmp_path / folder / "progress.csv").filter(like="rollout/") for folder in ("old", "new")]
    pd.testing.assert_frame_equal(*logs)
    grid_graph(old)
    grid_graph(new)
    for in_predict in (False, True):
        old.planner.in_predict = new.planner.in_predict = in_predict
        np.testing.assert_array_equal(rollout_actions(old, short_maze(seed=4)), rollout_actions(new, short_maze(seed=4)))


def test_a_deprecated_planning_parameter_replaces_its_planner_kwargs_key():
    """A YAML entry's planner_kwargs with the zoo's ``-params planning:'off'`` on top: the parameter wins."""
    with pytest.warns(DeprecationWarning, match=r"planning is deprecated: pass planner_kwargs=\{'mode': 'off'\}"):
        model = tiny_model(DIPPER, short_maze(), planner_kwargs=dict(mode="subgoal", lookahead=2), planning="off")
    assert model.planner_kwargs == dict(mode="off", lookahead=2) and model.planner.graph is None


def test_the_planning_attributes_are_the_planners_and_warn(maze_env):
    model = tiny_model(DIPPER, maze_env, planner_kwargs=dict(mode="subgoal", lookahead=2))
    attributes = dict(planning="mode", plan_in_predict="in_predict", planning_lookahead="lookahead")
    attributes.update(planning_resolution="resolution", planning_value_threshold="value_threshold", subgoal_graph="graph")
    for old, new in attributes.items():
        with pytest.warns(DeprecationWarning, match=f"DIPPER.{old} is deprecated: use model.planner.{new}"):
            assert getattr(model, old) is getattr(model.planner, new)
    with pytest.warns(DeprecationWarning, match="DIPPER.plan_in_predict is deprecated"):
        model.plan_in_predict = False
    assert model.planner.in_predict is False and not model._predict_plans()
    with pytest.warns(DeprecationWarning):
        model.subgoal_graph = None
    assert model.planner.graph is None


@pytest.mark.parametrize(
    "planner_kwargs, error, message",
    [
        (dict(mode="graph"), ValueError, r"Unknown planning mode 'graph': choose one of \('off', 'subgoal', 'waypoint'\)"),
        (dict(mode="subgoal", lookahead=0), ValueError, "lookahead must be at least 1"),
        (dict(mode="subgoal", lookahead=1.5), ValueError, r"lookahead must be a whole number"),
        (dict(mode="subgoal", resolution=0.0), ValueError, "resolution must be a finite number > 0"),
        (dict(mode="subgoal", value_threshold=math.nan), ValueError, "value_threshold must be a finite number"),
        (dict(mode="subgoal", look_ahead=2), TypeError, "SubgoalPlanner got an unexpected keyword argument 'look_ahead'"),
    ],
)
def test_planner_kwargs_are_checked_at_construction(maze_env, planner_kwargs, error, message):
    with pytest.raises(error, match=message):
        tiny_model(DIPPER, maze_env, planner_kwargs=planner_kwargs)


def test_whole_floats_and_strings_for_the_lookahead_become_ints(maze_env):
    assert tiny_model(DIPPER, maze_env, planner_kwargs=dict(mode="subgoal", lookahead=2.0)).planner.lookahead == 2
    with pytest.warns(DeprecationWarning):
        assert tiny_model(DIPPER, maze_env, planning="subgoal", planning_lookahead="3").planner.lookahead == 3


def with_the_attributes_before_planner_kwargs(new_zip: Path, old_zip: Path, graph: SubgoalGraph) -> None:
    """``new_zip`` rewritten as DIPPER saved models before ``planner_kwargs``: the planning settings and the graph as
    attributes of the model (NEW_FORM's settings), no planner."""
    with zipfile.ZipFile(new_zip) as archive:
        files = {name: archive.read(name) for name in archive.namelist()}
    data = json.loads(files["data"])
    assert "planner" in data and "planner_kwargs" in data
    del data["planner"], data["planner_kwargs"]
    attributes = dict(
        planning="subgoal",
        plan_in_predict=False,
        planning_lookahead=2,
        planning_resolution=None,
        planning_value_threshold=-12.0,
        subgoal_graph=graph,
        _trajectories_since_graph=3,
    )
    data.update(json.loads(data_to_json(attributes)))
    files["data"] = json.dumps(data).encode()
    with zipfile.ZipFile(old_zip, "w") as archive:
        for name, content in files.items():
            archive.writestr(name, content)


def test_a_model_saved_before_planner_kwargs_loads_and_plans_as_it_did(tmp_path):
    model = tiny_model(DIPPER, one_room_maze(), planner_kwargs=NEW_FORM)
    model.learn(400)
    grid_graph(model)
    model.planner.in_predict = True  # so that predict plans, and the actions tell whether the graph came along
    model.save(tmp_path / "new.zip")
    with_the_attributes_before_planner_kwargs(tmp_path / "new.zip", tmp_path / "old.zip", model.planner.graph)

    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)  # loading an old file is no deprecated use
        loaded = DIPPER.load(tmp_path / "old.zip", env=one_room_maze())
    assert loaded.planner_kwargs == {**NEW_FORM, "resolution": None}
    assert not {"planning", "subgoal_graph", "_trajectories_since_graph"} & set(vars(loaded))
    np.testing.assert_array_equal(loaded.planner.graph.edges, model.planner.graph.edges)
    assert loaded.planner.in_predict is False and loaded.planner.value_threshold == -12.0
    loaded.planner.in_predict = True
    np.testing.assert_array_equal(rollout_actions(loaded, short_maze(seed=4)), rollout_actions(model, short_maze(seed=4)))
    # It trains on, and saves in the new form.
    loaded.learn(100, reset_num_timesteps=False)
    loaded.save(tmp_path / "again.zip")
    assert DIPPER.load(tmp_path / "again.zip").planner.lookahead == 2


def test_planner_kwargs_given_to_load_keep_the_saved_graph_only_where_its_voxels_are_theirs(tmp_path):
    model = tiny_model(DIPPER, one_room_maze(), planner_kwargs=dict(mode="subgoal", resolution=0.5))
    grid_graph(model)
    model.save(tmp_path / "model.zip")

    same_voxels = DIPPER.load(tmp_path / "model.zip", planner_kwargs={"lookahead": 2})
    np.testing.assert_array_equal(same_voxels.planner.graph.edges, model.planner.graph.edges)

    with pytest.warns(UserWarning, match=r"voxels of 0\.5 over .*ask for 2 over .*replaced by an empty graph"):
        coarser = DIPPER.load(tmp_path / "model.zip", planner_kwargs={"resolution": 2.0})
    assert coarser.planner.graph.resolution == 2.0 and len(coarser.planner.graph) == 0
    assert coarser.planner_kwargs["resolution"] == 2.0

    # Without planning the model keeps no graph, so that it plans nowhere and exports.
    off = DIPPER.load(tmp_path / "model.zip", planner_kwargs={"mode": "off"})
    assert off.planner.graph is None and not off.planner.plans_in_predict
    off.export_policy()


# ------------------------------------------------------------------------------- switch_kwargs, and the form before it

OLD_SWITCHES = dict(nll_coef=1.0, hindsight_actions=True, truncate_at_goal=True, value_reg="score")


def test_the_switches_as_parameters_still_work_and_warn_naming_switch_kwargs(tmp_path):
    """Given to the constructor (the old name winning over its key), read and set as attributes, the same run."""
    message = (
        "DIPPER's nll_coef, hindsight_actions, truncate_at_goal, value_reg are deprecated: pass switch_kwargs="
        "{'nll_coef': 1.0, 'hindsight_actions': True, 'truncate_at_goal': True, 'value_reg': 'score'} instead"
    )
    with pytest.warns(DeprecationWarning, match=re.escape(message)):
        old = tiny_model(DIPPER, short_maze(), switch_kwargs=dict(nll_coef=0.5, label_smoothing=0.1), **OLD_SWITCHES)
    old.set_logger(configure(str(tmp_path / "old"), ["csv"]))
    old.learn(300, log_interval=1)
    new = tiny_model(DIPPER, short_maze(), switch_kwargs=dict(**OLD_SWITCHES, label_smoothing=0.1))
    new.set_logger(configure(str(tmp_path / "new"), ["csv"]))
    new.learn(300, log_interval=1)
    assert old.switch_kwargs == new.switch_kwargs == {**DEFAULT_SWITCH_KWARGS, **OLD_SWITCHES, "label_smoothing": 0.1}
    logs = [pd.read_csv(tmp_path / folder / "progress.csv").filter(like="train/high") for folder in ("old", "new")]
    assert "train/high_nll" in logs[0]
    pd.testing.assert_frame_equal(*logs)

    with pytest.warns(DeprecationWarning, match=r"DIPPER.nll_coef is deprecated: use model.switch_kwargs\['nll_coef'\]"):
        assert old.nll_coef == 1.0
    with pytest.warns(DeprecationWarning, match=r"DIPPER.reference is deprecated: use model.switch_kwargs\['reference'\]"):
        old.reference = "averaged"
    assert old.switch_kwargs["reference"] == "averaged"
    with pytest.raises(TypeError, match="goal_episode_prob"):  # a switch born in switch_kwargs has no older form
        tiny_model(DIPPER, short_maze(), goal_episode_prob=0.5)
    # The model has no averaged actor: the switch, now set, is refused when it would act.
    with pytest.raises(ValueError, match=r"switch_kwargs\['reference'\]='averaged' needs an averaged actor"):
        old.learn(10)


def test_a_model_saved_before_switch_kwargs_loads_with_its_switches(tmp_path):
    model = tiny_model(DIPPER, short_maze(), switch_kwargs=dict(OLD_SWITCHES))
    model.learn(100)
    model.save(tmp_path / "new.zip")
    # The file as DIPPER wrote it before switch_kwargs: each switch an attribute of its own.
    saved_in_old_form(
        tmp_path / "new.zip",
        tmp_path / "old.zip",
        "switch_kwargs",
        newer_keys=("goal_episode_prob", "contrast_env_goals", "anchor_coef", "matched_control_prob", "twin_episodes"),
    )

    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)  # loading an old file is no deprecated use
        loaded = DIPPER.load(tmp_path / "old.zip", env=short_maze())
    assert loaded.switch_kwargs == model.switch_kwargs and not set(DEFAULT_SWITCH_KWARGS) & set(vars(loaded))
    loaded.learn(100, reset_num_timesteps=False)
    # A deprecated name given to load changes its key only, over the file's switches in either form.
    for path in ("old.zip", "new.zip"):
        with pytest.warns(DeprecationWarning, match=r"pass switch_kwargs=\{'nll_coef': 2.0\} instead"):
            reloaded = DIPPER.load(tmp_path / path, nll_coef=2.0)
        assert reloaded.switch_kwargs == {**model.switch_kwargs, "nll_coef": 2.0}, path
