"""FrankaKitchenMicrowaveBurner-v0: the Franka kitchen as a flat SB3 goal env, success only in task order, its expert."""

import pickle
import warnings

import gymnasium as gym
import mujoco
import numpy as np
import pytest
from stable_baselines3.common.env_checker import check_env

import sb3_dipper  # noqa: F401  (registers the env ids)
from sb3_dipper import DIPPER
from sb3_dipper.common.subgoals import ElementSubgoalSpace, SubgoalSpace
from sb3_dipper.envs import EXPERTS
from sb3_dipper.envs.kitchen import ENV_ID, FrankaKitchenMicrowaveBurnerExpert, FrankaKitchenOrderedEnv
from tests.conftest import tiny_model

# qpos addresses of the microwave hinge and of the bottom burner's knob and slide (the achieved goal, in this order).
MICROWAVE, KNOB, SLIDE = 22, 11, 12
GOAL = np.array([-0.75, -0.88, -0.01])
# Joint values that complete an element (within 0.3 of the goal) and values that do not.
DOOR_OPEN, DOOR_SHUT = -0.7, 0.0
KNOB_ON, KNOB_OFF = -0.9, 0.0


@pytest.fixture(scope="module")
def env():
    env = gym.make(ENV_ID)
    yield env
    env.close()


def set_elements(env: gym.Env, door: float | None = None, knob: float | None = None) -> None:
    """Put the microwave door and the bottom burner's knob at the given angles (at rest)."""
    kitchen = env.unwrapped
    if door is not None:
        kitchen.data.qpos[MICROWAVE] = door
    if knob is not None:
        kitchen.data.qpos[KNOB] = knob
        # The oven's equality constraint ties the burner's slide to its knob: slide = knob / 174.
        kitchen.data.qpos[SLIDE] = knob / 174.0
    kitchen.data.qvel[:] = 0.0
    mujoco.mj_forward(kitchen.model, kitchen.data)


def hold(env: gym.Env) -> tuple[float, dict]:
    """One step without moving the arm; the reward and the info."""
    _, reward, terminated, truncated, info = env.step(np.zeros(9, dtype=np.float32))
    assert not terminated and not truncated
    return reward, info


def test_passes_sb3_env_checker():
    # With warnings as errors: no nested Dict, no float64 action space.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(FrankaKitchenOrderedEnv(), warn=True)


def test_registered_with_a_time_limit_and_flat_goal_spaces(env):
    assert env.spec.max_episode_steps == 225
    assert env.spec.entry_point == "sb3_dipper.envs.kitchen:FrankaKitchenOrderedEnv"
    expected = {"observation": (59,), "achieved_goal": (3,), "desired_goal": (3,)}
    for key, shape in expected.items():
        space = env.observation_space[key]
        assert isinstance(space, gym.spaces.Box) and space.shape == shape and space.dtype == np.float64
    assert env.action_space == gym.spaces.Box(-1.0, 1.0, (9,), np.float32)
    obs, info = env.reset(seed=0)
    assert {key: value.shape for key, value in obs.items()} == expected
    np.testing.assert_array_equal(obs["desired_goal"], GOAL)
    np.testing.assert_array_equal(obs["achieved_goal"], env.unwrapped.data.qpos[[MICROWAVE, KNOB, SLIDE]])
    assert info["is_success"] == 0.0 and info["episode_task_completions"] == []
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert obs["observation"].shape == (59,) and isinstance(reward, float) and reward == -1.0
    assert not terminated and not truncated and isinstance(info["is_success"], float)


def test_compute_reward_is_vectorised_and_matches_single_calls(env):
    kitchen = env.unwrapped
    rng = np.random.default_rng(0)
    space = kitchen.subgoal_space
    achieved = rng.uniform(space.low, space.high, (64, 3))
    achieved[:8] = GOAL + rng.uniform(-0.15, 0.15, (8, 3))
    desired = np.broadcast_to(GOAL, achieved.shape)
    batch = kitchen.compute_reward(achieved, desired, [{}] * 64)
    single = [kitchen.compute_reward(a, d, {}) for a, d in zip(achieved, desired, strict=True)]
    assert batch.shape == (64,)
    np.testing.assert_array_equal(batch, single)
    assert set(np.unique(batch)) == {-1.0, 0.0} and np.all(batch[:8] == 0.0)
    # Any leading dimensions.
    np.testing.assert_array_equal(
        kitchen.compute_reward(achieved.reshape(4, 16, 3), desired.reshape(4, 16, 3), None), batch.reshape(4, 16)
    )
    # Each element is judged by the norm over its joints: 0.25 and 0.2 off on the burner's two joints is 0.32 > 0.3.
    cases = {
        (-0.75, -0.88, -0.01): 0.0,
        (-1.0, -0.65, -0.01): 0.0,
        (-0.75, -0.88 + 0.25, -0.01 + 0.2): -1.0,
        (-0.4, -0.88, -0.01): -1.0,
        (-0.75, 0.0, 0.0): -1.0,
    }
    for achieved_goal, reward in cases.items():
        assert kitchen.compute_reward(np.array(achieved_goal), GOAL, {}) == reward


def test_reward_is_order_free_but_success_is_not(env):
    env.reset(seed=0)
    set_elements(env, knob=KNOB_ON)
    reward, info = hold(env)
    assert reward == -1.0 and info["is_success"] == 0.0 and info["episode_task_completions"] == ["bottom burner"]
    set_elements(env, door=DOOR_OPEN)
    reward, info = hold(env)
    # Both elements are done now: the goal reward is 0, but the burner came first.
    assert reward == 0.0 and info["is_success"] == 0.0
    assert info["episode_task_completions"] == ["bottom burner", "microwave"]
    # Turning the burner off and on again does not repair the order.
    set_elements(env, knob=KNOB_OFF)
    assert hold(env) == (-1.0, {"is_success": 0.0, "episode_task_completions": ["bottom burner", "microwave"]})
    set_elements(env, knob=KNOB_ON)
    reward, info = hold(env)
    assert reward == 0.0 and info["is_success"] == 0.0
    # compute_reward is pure: calling it with completed goals records nothing.
    env.reset(seed=0)
    env.unwrapped.compute_reward(GOAL, GOAL, {})
    assert hold(env)[1]["episode_task_completions"] == []


def test_success_needs_the_microwave_before_the_burner_and_both_done_now(env):
    _, info = env.reset(seed=1)
    assert info["episode_task_completions"] == []
    set_elements(env, door=DOOR_OPEN)
    assert hold(env) == (-1.0, {"is_success": 0.0, "episode_task_completions": ["microwave"]})
    set_elements(env, knob=KNOB_ON)
    assert hold(env) == (0.0, {"is_success": 1.0, "episode_task_completions": ["microwave", "bottom burner"]})
    # Success is judged on the current state: shutting the door again undoes it.
    set_elements(env, door=DOOR_SHUT)
    assert hold(env)[1]["is_success"] == 0.0
    set_elements(env, door=DOOR_OPEN)
    assert hold(env)[1]["is_success"] == 1.0


def test_same_seed_same_observations():
    first, second = FrankaKitchenOrderedEnv(), FrankaKitchenOrderedEnv()
    actions = np.random.default_rng(0).uniform(-1, 1, (20, 9)).astype(np.float32)
    obs_a, _ = first.reset(seed=7)
    obs_b, _ = second.reset(seed=7)
    for action in actions:
        for key in obs_a:
            np.testing.assert_array_equal(obs_a[key], obs_b[key])
        obs_a, *_ = first.step(action)
        obs_b, *_ = second.step(action)
    # The seed drives upstream's observation noise.
    other, _ = second.reset(seed=8)
    again, _ = first.reset(seed=7)
    assert not np.array_equal(other["observation"], again["observation"])
    first.close()
    second.close()


def test_declares_its_subgoal_space(env):
    space = env.unwrapped.subgoal_space
    assert isinstance(space, SubgoalSpace) and space.dim == 3 and space.threshold == pytest.approx(0.3)
    # Joint ranges [-2.094, 0], [-1.57, 0] and [-0.009, 0] stretched to the goal (-0.01) with a 0.05 margin.
    np.testing.assert_allclose(space.low, [-2.144, -1.62, -0.06])
    np.testing.assert_allclose(space.high, [0.05, 0.05, 0.05])
    obs, _ = env.reset(seed=0)
    for goal in (obs["achieved_goal"], obs["desired_goal"]):
        assert np.all(space.low < goal) and np.all(goal < space.high)


def test_element_subgoals_ask_each_task_element_done_or_at_rest():
    element_env = gym.make(ENV_ID, element_subgoals=True)
    space = element_env.unwrapped.subgoal_space
    assert isinstance(space, ElementSubgoalSpace) and space.elements == ((0,), (1, 2))
    np.testing.assert_allclose(space.done, GOAL)
    obs, _ = element_env.reset(seed=0)
    np.testing.assert_allclose(space.start, obs["achieved_goal"], atol=1e-3)
    # Hinge asked done, knob at rest: reached with the door open and the knob off, not with both done.
    door_only = space.to_world(np.array([0.5, -0.5, 0.5]))
    np.testing.assert_allclose(door_only, [GOAL[0], *space.start[1:]], atol=1e-6)
    still = np.zeros(9, dtype=np.float32)
    set_elements(element_env, door=DOOR_OPEN, knob=KNOB_OFF)
    door_open, *_ = element_env.step(still)
    set_elements(element_env, door=DOOR_OPEN, knob=KNOB_ON)
    both_done, *_ = element_env.step(still)
    assert space.compute_reward(door_open["achieved_goal"], door_only) == 0.0
    assert space.compute_reward(both_done["achieved_goal"], door_only) == -1.0
    assert space.compute_reward(both_done["achieved_goal"], space.to_world(np.ones(3))) == 0.0
    element_env.close()


@pytest.mark.parametrize("mode", ["off", "subgoal"])
def test_dipper_proposes_only_element_subgoals(mode):
    element_env = gym.make(ENV_ID, element_subgoals=True, max_episode_steps=45)
    model = tiny_model(DIPPER, element_env, option_steps=15, planner_kwargs=dict(mode=mode))
    model.learn(300)
    space = model.subgoal_space
    combinations = space.to_world(np.array([[1.0, 1.0, 1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, 1.0], [-1.0, -1.0, -1.0]]))
    buffer = model.lower.replay_buffer
    proposed = buffer.observations["desired_goal"][: buffer.pos, 0]
    assert len(proposed) == 300
    assert np.all(np.isclose(proposed[:, None], combinations[None], atol=1e-6).all(-1).any(-1))
    element_env.close()


def test_tasks_and_upstream_arguments():
    with pytest.raises(ValueError, match="Unknown tasks"):
        FrankaKitchenOrderedEnv(tasks=("microwave", "fridge"))
    with pytest.raises(ValueError, match="without repetitions"):
        FrankaKitchenOrderedEnv(tasks=("microwave", "microwave"))
    # The order is the tasks' order; the noise ratios reach upstream (no noise: the observation is the state).
    reversed_env = FrankaKitchenOrderedEnv(tasks=("bottom burner", "microwave"), robot_noise_ratio=0.0, object_noise_ratio=0.0)
    obs, _ = reversed_env.reset(seed=0)
    np.testing.assert_array_equal(obs["observation"][:9], reversed_env.data.qpos[:9])
    np.testing.assert_array_equal(obs["desired_goal"], [-0.88, -0.01, -0.75])
    set_elements(reversed_env, knob=KNOB_ON)
    hold(reversed_env)
    set_elements(reversed_env, door=DOOR_OPEN)
    assert hold(reversed_env)[1]["is_success"] == 1.0
    # Pickling rebuilds the env with its own arguments.
    copy = pickle.loads(pickle.dumps(reversed_env))
    assert type(copy) is FrankaKitchenOrderedEnv and copy.tasks == ("bottom burner", "microwave")
    assert copy.robot_env.robot_noise_ratio == 0.0
    # The expert only knows the microwave-then-burner task.
    with pytest.raises(ValueError, match="solves the tasks"):
        FrankaKitchenMicrowaveBurnerExpert(reversed_env)
    copy.close()
    reversed_env.close()


def test_renders_headless():
    env = gym.make(ENV_ID, render_mode="rgb_array", width=64, height=64)
    env.reset(seed=0)
    frame = env.render()
    env.close()
    assert frame.shape == (64, 64, 3) and frame.dtype == np.uint8 and frame.std() > 0


def run_expert(env: gym.Env, seeds: range) -> list[dict]:
    expert = EXPERTS[ENV_ID](env.unwrapped)
    final_infos = []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        expert.reset()
        done = False
        while not done:
            action = expert.act(obs)
            assert env.action_space.contains(action)
            obs, _, terminated, truncated, info = env.step(action)
            done = terminated or truncated
        final_infos.append(info)
    return final_infos


def test_scripted_expert_opens_the_microwave_then_turns_on_the_burner(env):
    assert EXPERTS[ENV_ID] is FrankaKitchenMicrowaveBurnerExpert
    for info in run_expert(env, range(5)):
        # Only the task's keys: the module's shared env may carry keys other tests' wrappers wrote into its info dict.
        assert {key: info[key] for key in ("is_success", "episode_task_completions")} == {
            "is_success": 1.0,
            "episode_task_completions": ["microwave", "bottom burner"],
        }


@pytest.mark.slow
def test_scripted_expert_succeeds_from_every_seed(env):
    assert all(info["is_success"] == 1.0 for info in run_expert(env, range(5, 30)))
