import json
import os
import zipfile
from pathlib import Path

# Headless MuJoCo rendering; set before mujoco is imported anywhere.
os.environ.setdefault("MUJOCO_GL", "egl")
# One torch thread in every process a test starts too (scripts, zoo runs): with both cores busy running the test
# workers, a second thread per process spins against the other worker's and a tiny run takes ten times as long.
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import pytest
import torch as th
from stable_baselines3 import HerReplayBuffer
from stable_baselines3.common.env_util import make_vec_env

import sb3_dipper
from sb3_dipper import DAC, DIPPER, HAC, HIER, PIPER, RAPS, SAGA, DPOFlat, SACDemo
from sb3_dipper.common.hierarchical import HierarchicalAlgorithm

TOOLS_DIR = Path(__file__).resolve().parent / "tools"

# One thread: tests run tiny networks, where more threads only add overhead and timing noise.
th.set_num_threads(1)

# RAPS has no learned lower level; tests/test_raps.py covers its runs, saving and determinism.
HIERARCHICAL_ALGORITHMS = [DIPPER, HIER, PIPER, SAGA, HAC]

# Tiny budgets: 20-step episodes of four 5-step options, small networks and buffers.
SHORT_EPISODES = {"max_episode_steps": 20}
TINY_KWARGS = {
    DIPPER: dict(n_preference_pairs=200, pairs_per_batch=8, trajectory_buffer_size=50, policy_kwargs=dict(net_arch=[16])),
    HIER: dict(high_batch_size=16, high_buffer_size=1000, policy_kwargs=dict(net_arch=[16])),
    PIPER: dict(
        high_batch_size=16,
        high_buffer_size=1000,
        policy_kwargs=dict(net_arch=[16]),
        n_preference_pairs=200,
        reward_batch_size=8,
        trajectory_buffer_size=50,
        reward_model_kwargs=dict(net_arch=[16]),
    ),
    HAC: dict(high_batch_size=16, high_buffer_size=1000, policy_kwargs=dict(net_arch=[16])),
    SAGA: dict(
        high_batch_size=16, high_buffer_size=1000, policy_kwargs=dict(net_arch=[16]), discriminator_kwargs=dict(net_arch=[16])
    ),
}


def tiny_model(model_class, env, policy="MultiInputPolicy", **overrides):
    kwargs = dict(
        option_steps=5,
        learning_starts=40,
        buffer_size=2000,
        batch_size=16,
        low_policy_kwargs=dict(net_arch=[16]),
        seed=0,
        **TINY_KWARGS[model_class],
    )
    kwargs.update(overrides)
    return model_class(policy, env, **kwargs)


# Every algorithm of the package. RAPS has no learned lower level and DAC, DPOFlat, SACDemo are flat, so their tiny
# models are built here rather than through `tiny_model`. SACDemo's clones the task's single demonstration.
ALL_ALGORITHMS = [*HIERARCHICAL_ALGORITHMS, RAPS, DAC, DPOFlat, SACDemo]
# Algorithms with an option layer (RAPS's lower level is scripted); DAC, DPOFlat and SACDemo act with one primitive step each.
OPTION_ALGORITHMS = [model_class for model_class in ALL_ALGORITHMS if issubclass(model_class, HierarchicalAlgorithm)]
OTHER_TINY_MODELS = {
    RAPS: dict(option_steps=5, high_batch_size=16, high_buffer_size=1000),
    DAC: dict(buffer_size=2000, batch_size=16, replay_buffer_class=HerReplayBuffer, discriminator_net_arch=[16]),
    DPOFlat: dict(segment_length=5, n_preference_pairs=200, pairs_per_batch=8, trajectory_buffer_size=50),
    SACDemo: dict(buffer_size=2000, batch_size=16, replay_buffer_class=HerReplayBuffer, demo_kwargs=dict(demo_path="auto")),
}


def any_tiny_model(model_class, env, policy="MultiInputPolicy", **overrides):
    """A test-sized model of any algorithm of the package."""
    if model_class in TINY_KWARGS:
        return tiny_model(model_class, env, policy, **overrides)
    kwargs = dict(learning_starts=40, policy_kwargs=dict(net_arch=[16]), seed=0, **OTHER_TINY_MODELS[model_class])
    kwargs.update(overrides)
    return model_class(policy, env, **kwargs)


def short_maze(n_envs: int = 1, seed: int = 0, **kwargs):
    return make_vec_env("sb3_dipper:PointMazeFourRooms-v0", n_envs=n_envs, seed=seed, env_kwargs=SHORT_EPISODES, **kwargs)


def tiny_pick_and_place_model(env_id: str = "FetchPickAndPlaceFixed-v0") -> DIPPER:
    """A test-sized DIPPER on a Fetch pick-and-place with the zoo entries' episodes: 7 options of 7 steps."""
    env = make_vec_env(env_id, n_envs=1, seed=0, env_kwargs=dict(max_episode_steps=49))
    return DIPPER(
        "MultiInputPolicy", env, option_steps=7, learning_starts=50, batch_size=16, buffer_size=500, seed=0,
        n_preference_pairs=50, pairs_per_batch=4, trajectory_buffer_size=20,
        low_policy_kwargs=dict(net_arch=[16]), policy_kwargs=dict(net_arch=[16]),
    )  # fmt: skip


@pytest.fixture
def maze_env():
    env = short_maze()
    yield env
    env.close()


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Marks the tests of tests/tools/ ``tools``, and leaves ``slow`` tests out unless ``-m`` names ``slow``.

    ``slow`` is opt-in here rather than through ``addopts = -m 'not slow'``, which any ``-m`` given on the command line
    replaces: ``pytest tests -m "not tools"`` runs the library's tests without the slow ones too.
    """
    for item in items:
        if TOOLS_DIR in item.path.parents:
            item.add_marker(pytest.mark.tools)
    if "slow" in config.getoption("markexpr"):
        return
    kept = [item for item in items if item.get_closest_marker("slow") is None]
    if len(kept) < len(items):
        config.hook.pytest_deselected(items=[item for item in items if item.get_closest_marker("slow") is not None])
        items[:] = kept


__all__ = [
    "ALL_ALGORITHMS",
    "HIERARCHICAL_ALGORITHMS",
    "OPTION_ALGORITHMS",
    "any_tiny_model",
    "sb3_dipper",
    "short_maze",
    "tiny_model",
]


def saved_in_old_form(path, old_path, group, newer_keys=()):
    """Rewrite the model file ``path`` at ``old_path`` as it was saved before the dict parameter ``group`` existed:
    each of its keys an attribute of its own in the saved data, but ``newer_keys``, which came after the dict did."""
    with zipfile.ZipFile(path) as archive:
        files = {name: archive.read(name) for name in archive.namelist()}
    data = json.loads(files["data"])
    data.update({key: value for key, value in data.pop(group).items() if key not in newer_keys})
    files["data"] = json.dumps(data).encode()
    with zipfile.ZipFile(old_path, "w") as archive:
        for name, content in files.items():
            archive.writestr(name, content)
