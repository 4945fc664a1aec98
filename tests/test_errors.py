"""Bad input gets an error that names the problem and the fix; every algorithm checks its env and policy (as SB3's
test_envs.py and test_predict.py)."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces
from stable_baselines3.td3.policies import MultiInputPolicy as TD3MultiInputPolicy

from sb3_dipper import DIPPER, HIER, SubgoalSpace
from tests.conftest import ALL_ALGORITHMS, OPTION_ALGORITHMS, any_tiny_model, short_maze, tiny_model


class NestedGoalEnv(gym.Env):
    """Goals as nested Dicts, as FrankaKitchen-v1 has them."""

    observation_space = spaces.Dict(
        {
            "observation": spaces.Box(-1, 1, (3,)),
            "achieved_goal": spaces.Dict({"microwave": spaces.Box(-1, 1, (1,))}),
            "desired_goal": spaces.Dict({"microwave": spaces.Box(-1, 1, (1,))}),
        }
    )
    action_space = spaces.Box(-1, 1, (2,))


class DenseGoalEnv(gym.Env):
    """A goal env with a dense reward, which primitive-in-the-loop labels cannot use."""

    observation_space = spaces.Dict({key: spaces.Box(-1, 1, (2,)) for key in ("observation", "achieved_goal", "desired_goal")})
    action_space = spaces.Box(-1, 1, (2,))
    spec = gym.envs.registration.EnvSpec("DenseGoal-v0", max_episode_steps=10)
    subgoal_space = SubgoalSpace(np.full(2, -1.0), np.full(2, 1.0), 0.1)

    def compute_reward(self, achieved_goal, desired_goal, info):
        return -np.linalg.norm(achieved_goal - desired_goal, axis=-1)


class GoalEnvWithoutReward(gym.Env):
    """A goal env with everything the algorithms need but a vectorised ``compute_reward(achieved, desired, info)``."""

    observation_space = DenseGoalEnv.observation_space
    action_space = DenseGoalEnv.action_space
    spec = gym.envs.registration.EnvSpec("GoalWithoutReward-v0", max_episode_steps=10)
    subgoal_space = DenseGoalEnv.subgoal_space


class GoalEnvWithTwoArgumentReward(GoalEnvWithoutReward):
    def compute_reward(self, achieved_goal, desired_goal):
        return -(np.linalg.norm(achieved_goal - desired_goal, axis=-1) > 0.1).astype(np.float64)


class GoalEnvWithUnbatchedReward(GoalEnvWithoutReward):
    def compute_reward(self, achieved_goal, desired_goal, info):
        return -float(np.linalg.norm(achieved_goal - desired_goal) > 0.1)


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
@pytest.mark.parametrize(
    "env_class, failure",
    [
        (GoalEnvWithoutReward, "failed: .*compute_reward"),
        (GoalEnvWithTwoArgumentReward, "failed: .*positional argument"),
        (GoalEnvWithUnbatchedReward, r"gave rewards of shape \(\)"),
    ],
)
def test_an_env_without_a_vectorised_compute_reward_is_refused_at_construction(model_class, env_class, failure):
    # HER calls compute_reward only at its first update, after learning_starts, and failed there inside SB3.
    with pytest.raises(ValueError, match=rf"{model_class.__name__} needs the goal env's compute_reward.*{failure}"):
        any_tiny_model(model_class, env_class())


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_a_non_goal_env_is_refused(model_class):
    with pytest.raises(ValueError, match="needs a goal-conditioned env"):
        model_class("MlpPolicy", "Pendulum-v1")


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_a_nested_dict_goal_env_is_refused(model_class):
    with pytest.raises(ValueError, match=r"nested Dict.*FrankaKitchenMicrowaveBurner"):
        model_class("MlpPolicy", NestedGoalEnv())


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_an_unknown_policy_name_is_refused(model_class, maze_env):
    with pytest.raises(ValueError, match=rf"{model_class.__name__} has no policy 'CnnPolicy'"):
        model_class("CnnPolicy", maze_env)


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_another_algorithms_policy_class_is_refused_naming_the_alias(model_class, maze_env):
    refusal = rf"^{model_class.__name__}'s policy must be one of \[.*'MultiInputPolicy'.*got <class.*, env\)"
    with pytest.raises(TypeError, match=refusal):
        model_class(TD3MultiInputPolicy, maze_env)


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_a_mismatched_env_at_load_is_refused(model_class, tmp_path, maze_env):
    model = any_tiny_model(model_class, maze_env)
    model.save(tmp_path / "model")
    # Spaces are compared before the time limit: an env of another task with another episode length is told that its
    # spaces differ, not to change its episode length.
    for other in (gym.make("FetchReach-v4", max_episode_steps=20), gym.make("FetchReach-v4", max_episode_steps=30)):
        with pytest.raises(ValueError, match=r"^Observation spaces do not match"):
            model_class.load(tmp_path / "model", env=other)
        with pytest.raises(ValueError, match=r"^Observation spaces do not match"):
            model.set_env(other)


# DAC and DPOFlat predict with SB3's policies, which fail on a flat observation as SB3's SAC does (an IndexError).
@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_predict_on_a_flat_observation_names_the_dict_it_needs(model_class, maze_env):
    model = any_tiny_model(model_class, maze_env)
    with pytest.raises(TypeError, match="goal env's Dict observations, got ndarray"):
        model.predict(np.zeros(maze_env.observation_space["observation"].shape))


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_predict_names_the_key_of_a_bad_observation(model_class, maze_env):
    model = any_tiny_model(model_class, maze_env)
    observation = maze_env.reset()
    without_goal = {key: value for key, value in observation.items() if key != "desired_goal"}
    with pytest.raises(ValueError, match=r"keys must be the env's .*; it lacks \['desired_goal'\]"):
        model.predict(without_goal)
    with pytest.raises(ValueError, match=r"it has keys the env does not: \['extra'\]"):
        model.predict({**observation, "extra": np.zeros(1)})
    # One env's observation with twice its entries (it was named as another key's mistake).
    doubled = {**observation, "observation": np.zeros(2 * observation["observation"].shape[-1])}
    with pytest.raises(ValueError, match=r"observation\['observation'\] has shape \(8,\), the env's is \(4,\)"):
        model.predict(doubled)
    unbatched_goal = {**observation, "desired_goal": observation["desired_goal"][0]}
    with pytest.raises(ValueError, match="keys are for different numbers of envs"):
        model.predict(unbatched_goal)
    nan = {**observation, "observation": np.full_like(observation["observation"], np.nan)}
    with pytest.raises(ValueError, match="predict's observation key 'observation' holds NaN"):
        model.predict(nan)


@pytest.mark.parametrize("model_class", OPTION_ALGORITHMS)
def test_predict_refuses_a_state_or_episode_start_of_other_envs(model_class):
    env = short_maze(n_envs=2)
    model = any_tiny_model(model_class, env)
    observation = env.reset()
    _, state = model.predict(observation)
    one_env = {key: value[:1] for key, value in observation.items()}
    with pytest.raises(ValueError, match=r"state must be .* for this observation's 1 env\(s\).*pass state=None"):
        model.predict(one_env, state=state)
    # A single flag used to start a new option in every env, cutting the other env's option short.
    with pytest.raises(ValueError, match="episode_start has 1 entries for 2 envs"):
        model.predict(observation, state=state, episode_start=np.array([True]))
    model.predict(observation, state=state, episode_start=np.array([True, False]))


def test_bad_dipper_switches_are_refused(maze_env):
    with pytest.raises(ValueError, match=r"Unknown switch_kwargs\['value_reg'\] 'papper'"):
        DIPPER("MlpPolicy", maze_env, switch_kwargs=dict(value_reg="papper"))
    with pytest.raises(ValueError, match=r"hindsight_goal_prob must be a finite number in \[0, 1\]"):
        DIPPER("MlpPolicy", maze_env, hindsight_goal_prob=1.5)
    with pytest.raises(ValueError, match="option_steps must be at least 1"):
        HIER("MlpPolicy", maze_env, option_steps=0)


def test_a_dense_reward_is_refused_for_preference_labels():
    with pytest.raises(
        ValueError, match=r"sparse goal reward.*Use the env.s sparse id \(FetchReach-v4, not FetchReachDense-v4\)"
    ):
        DIPPER("MlpPolicy", DenseGoalEnv())


def test_an_env_without_time_limit_needs_max_episode_steps():
    env = DenseGoalEnv()
    env.spec = gym.envs.registration.EnvSpec("DenseGoal-v0", max_episode_steps=None)
    with pytest.raises(ValueError, match="no time limit"):
        HIER("MlpPolicy", env)


class UnboundedGoalEnv(gym.Env):
    """A sparse goal env that declares no subgoal space, with unbounded goals and no ``distance_threshold``."""

    observation_space = spaces.Dict(
        {key: spaces.Box(-np.inf, np.inf, (2,)) for key in ("observation", "achieved_goal", "desired_goal")}
    )
    action_space = spaces.Box(-1, 1, (2,))
    spec = gym.envs.registration.EnvSpec("UnboundedGoal-v0", max_episode_steps=10)

    def compute_reward(self, achieved_goal, desired_goal, info):
        return -(np.linalg.norm(achieved_goal - desired_goal, axis=-1) > 0.1).astype(np.float32)


def test_an_env_without_a_known_subgoal_space():
    with pytest.raises(ValueError, match="No subgoal space is known for env 'UnboundedGoal-v0'"):
        HIER("MlpPolicy", UnboundedGoalEnv())


def test_learn_without_env_explains_itself(tmp_path, maze_env):
    tiny_model(HIER, maze_env).save(tmp_path / "model")
    loaded = HIER.load(tmp_path / "model")
    with pytest.raises(ValueError, match=r"learn\(\) needs an env.*HIER.load\(path, env=...\)"):
        loaded.learn(10)


def test_short_maze_fixture_is_short():
    env = short_maze()
    assert env.get_attr("spec")[0].max_episode_steps == 20
