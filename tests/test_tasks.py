"""DIPPER and HIER train on every task of the paper by env id, with and without the default demonstration."""

import numpy as np
import pytest
from stable_baselines3.common.env_util import make_vec_env

from sb3_dipper import DIPPER, HIER
from tests.conftest import tiny_model

# (env id, option steps K as in the paper, has a scripted expert for demonstrations)
TASKS = [
    ("FetchFourRoomMaze-v0", 15, False),
    ("FetchPush-v4", 7, True),
    ("FetchPickAndPlace-v4", 7, True),
    ("FetchPushFixed-v0", 7, True),
    ("FetchPickAndPlaceFixed-v0", 7, True),
    ("FrankaKitchenMicrowaveBurner-v0", 15, True),
]
CASES = [(env_id, k, False) for env_id, k, _ in TASKS] + [(env_id, k, True) for env_id, k, demo in TASKS if demo]


@pytest.fixture(autouse=True)
def demo_cache(tmp_path_factory, monkeypatch):
    """Default demonstrations are generated on first use into one cache shared by this module's tests."""
    monkeypatch.setenv("SB3_DIPPER_CACHE", str(tmp_path_factory.getbasetemp() / "demos"))


@pytest.mark.parametrize("model_class", [DIPPER, HIER])
@pytest.mark.parametrize(("env_id", "option_steps", "with_demos"), CASES)
def test_trains_a_few_hundred_steps_on_every_task(model_class, env_id, option_steps, with_demos):
    env = make_vec_env(env_id, n_envs=1, seed=0, env_kwargs={"max_episode_steps": 2 * option_steps})
    demos = dict(demo_kwargs=dict(demo_path="auto", demo_share=0.25)) if with_demos else {}
    model = tiny_model(model_class, env, option_steps=option_steps, learning_starts=60, **demos)
    if with_demos:
        assert len(model.lower.demonstrations) > 0
    model.learn(200)
    assert model.num_timesteps >= 200
    observation = env.reset()
    action, state = model.predict(observation, deterministic=True)
    assert action.shape == (1, *env.action_space.shape) and np.all(np.isfinite(action))
    assert state is not None
    env.close()
