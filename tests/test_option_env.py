"""The option layer: K primitive steps per option, early ends, lower observations, one sink call per step."""

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

import sb3_dipper  # noqa: F401
from sb3_dipper.common.option_env import OptionVecEnv, PrimitiveTransition
from sb3_dipper.envs import PointMazeReachController


class RecordingSink:
    def __init__(self, keep_going: bool = True) -> None:
        self.transitions: list[PrimitiveTransition] = []
        self.keep_going = keep_going

    def __call__(self, transition: PrimitiveTransition) -> bool:
        self.transitions.append(transition)
        return self.keep_going


def make_option_env(n_envs=1, option_steps=10, max_episode_steps=25, vec_env_cls=DummyVecEnv, sink=None):
    # "module:id" makes a subprocess import sb3_dipper (and so register the id) before gym.make.
    venv = make_vec_env(
        "sb3_dipper:PointMazeFourRooms-v0",
        n_envs=n_envs,
        seed=0,
        vec_env_cls=vec_env_cls,
        env_kwargs={"max_episode_steps": max_episode_steps},
    )
    space = venv.get_attr("subgoal_space", indices=[0])[0]
    return OptionVecEnv(venv, space, option_steps, PointMazeReachController(), sink=sink)


def test_an_option_runs_exactly_k_primitive_steps():
    sink = RecordingSink()
    env = make_option_env(sink=sink)
    env.reset()
    _, _, dones, infos = env.step(np.zeros((1, 2), np.float32))
    assert len(sink.transitions) == 10 and infos[0]["option_steps"] == 10 and not dones[0]
    assert [bool(t.segment_ends[0]) for t in sink.transitions] == [False] * 9 + [True]


def test_an_option_ends_early_when_the_episode_ends():
    sink = RecordingSink()
    env = make_option_env(sink=sink)
    env.reset()
    lengths, dones = [], []
    for _ in range(3):
        _, _, done, infos = env.step(np.zeros((1, 2), np.float32))
        lengths.append(infos[0]["option_steps"])
        dones.append(bool(done[0]))
    assert lengths == [10, 10, 5] and dones == [False, False, True]
    assert len(sink.transitions) == 25


def test_the_lower_observation_pursues_the_subgoal():
    sink = RecordingSink()
    env = make_option_env(sink=sink)
    env.reset()
    actions = np.array([[0.5, -0.25]], np.float32)
    env.step(actions)
    subgoal = env.subgoal_space.to_world(actions)[0]
    for transition in sink.transitions:
        np.testing.assert_allclose(transition.low_obs["desired_goal"][0], subgoal)
        np.testing.assert_allclose(transition.next_low_obs["desired_goal"][0], subgoal)
        np.testing.assert_allclose(transition.low_obs["achieved_goal"][0], transition.low_obs["observation"][0, :2])
        distance = np.linalg.norm(transition.next_low_obs["achieved_goal"][0] - subgoal)
        assert transition.low_rewards[0] == (0.0 if distance <= env.subgoal_space.threshold else -1.0)
    # Consecutive primitive steps chain: each step starts where the previous one ended.
    for before, after in zip(sink.transitions, sink.transitions[1:], strict=False):
        np.testing.assert_allclose(before.next_low_obs["observation"], after.low_obs["observation"])


def test_the_last_transition_of_an_episode_ends_at_the_terminal_observation():
    sink = RecordingSink()
    env = make_option_env(sink=sink, option_steps=25)
    env.reset()
    obs, _, dones, infos = env.step(np.zeros((1, 2), np.float32))
    assert dones[0]
    terminal = infos[0]["terminal_observation"]
    np.testing.assert_allclose(sink.transitions[-1].next_low_obs["observation"][0], terminal["observation"])
    np.testing.assert_allclose(env.reached_obs["achieved_goal"][0], terminal["achieved_goal"])
    assert not np.allclose(obs["observation"][0], terminal["observation"])


def test_the_option_reports_its_subgoal_and_distance():
    env = make_option_env()
    env.reset()
    _, _, _, infos = env.step(np.array([[0.1, 0.2]], np.float32))
    expected = np.linalg.norm(env.reached_obs["achieved_goal"][0] - infos[0]["subgoal"])
    assert infos[0]["subgoal_distance"] == pytest.approx(expected)


def test_a_sink_can_stop_the_option():
    sink = RecordingSink(keep_going=False)
    env = make_option_env(sink=sink)
    env.reset()
    _, _, _, infos = env.step(np.zeros((1, 2), np.float32))
    assert len(sink.transitions) == 1 and infos[0]["option_interrupted"]


def test_two_envs_in_subprocesses_step_together():
    sink = RecordingSink()
    env = make_option_env(n_envs=2, vec_env_cls=SubprocVecEnv, sink=sink)
    try:
        obs = env.reset()
        assert obs["observation"].shape == (2, 4)
        actions = np.array([[0.5, 0.5], [-0.5, -0.5]], np.float32)
        obs, rewards, _, infos = env.step(actions)
        assert rewards.shape == (2,) and len(infos) == 2 and len(sink.transitions) == 10
        assert all(t.low_obs["observation"].shape == (2, 4) for t in sink.transitions)
        subgoals = env.subgoal_space.to_world(actions)
        np.testing.assert_allclose(sink.transitions[0].low_obs["desired_goal"], subgoals)
    finally:
        env.close()


class NaNAfter(gym.Wrapper):
    def __init__(self, env, step: int):
        super().__init__(env)
        self.nan_step, self.count = step, 0

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.count += 1
        if self.count >= self.nan_step:
            obs = dict(obs, observation=np.full_like(obs["observation"], np.nan))
        return obs, reward, terminated, truncated, info


def test_nan_observations_are_refused_with_the_key_named():
    venv = make_vec_env("PointMazeFourRooms-v0", n_envs=1, seed=0, wrapper_class=NaNAfter, wrapper_kwargs={"step": 3})
    env = OptionVecEnv(venv, venv.get_attr("subgoal_space")[0], 10, PointMazeReachController())
    env.reset()
    with pytest.raises(ValueError, match="'observation' holds NaN"):
        env.step(np.zeros((1, 2), np.float32))
