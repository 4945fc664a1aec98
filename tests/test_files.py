"""Files: crash-safe checkpoints, all-or-nothing buffer loading, streams, demonstration and preference files."""

import io
import pickle
import re
import shutil
import warnings

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common import save_util

from sb3_dipper import DAC, DIPPER, HAC, HIER, PIPER, RAPS, SAGA, DPOFlat, SACDemo
from sb3_dipper.common.demonstrations import load_demonstrations
from sb3_dipper.common.preferences import (
    PairShapes,
    PreferenceDataset,
    TrajectoryPairs,
    load_preference_data,
    save_preference_data,
)
from sb3_dipper.common.trajectories import TrajectoryBuffer
from sb3_dipper.envs.demos import default_demonstration_path, default_demonstrations, expert_demonstrations
from tests.conftest import any_tiny_model, short_maze, tiny_model

MAZE = "PointMazeFourRooms-v0"


class SimulatedKill(Exception):
    """Stands for the process being killed while a file is written."""


def files_of(folder):
    return {path.name: path.read_bytes() for path in sorted(folder.iterdir())}


def truncate(path, keep=0.5):
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


# ---------------------------------------------------------------------------------------------------- checkpoints


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """Tiny DIPPER and HIER after 60 steps (past learning_starts), each with a checkpoint of model and buffers."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        models = {}
        for model_class in (DIPPER, HIER):
            model = tiny_model(model_class, short_maze())
            model.learn(60)
            folder = tmp_path_factory.mktemp(model_class.__name__)
            model.save(folder / "model.zip")
            model.save_replay_buffer(folder / "buffer.pkl")
            models[model_class] = (model, folder)
    return models


def partial_pickle(obj, file, *args, **kwargs):
    file.write(b"\x80\x05partial")
    raise SimulatedKill


def partial_npz(file, *args, **kwargs):
    if hasattr(file, "write"):
        file.write(b"PK\x03\x04partial")
    else:  # a path, as numpy accepts
        with open(file, "wb") as opened:
            opened.write(b"PK\x03\x04partial")
    raise SimulatedKill


def partial_zip(*args, **kwargs):
    raise SimulatedKill  # called after the zip's data and parameters are written


@pytest.mark.parametrize(
    "model_class, writer, save",
    [
        (DIPPER, (pickle, "dump", partial_pickle), "buffers"),  # the lower replay buffer
        (DIPPER, (np, "savez_compressed", partial_npz), "buffers"),  # the higher level's trajectories and pairs
        (HIER, (pickle, "dump", partial_pickle), "buffers"),
        (DIPPER, (save_util, "get_system_info", partial_zip), "model"),
    ],
    ids=["lower-pickle", "high-npz", "hier-pickles", "model-zip"],
)
def test_a_save_killed_midway_leaves_the_previous_complete_files(trained, tmp_path, monkeypatch, model_class, writer, save):
    model, checkpoint = trained[model_class]
    for path in checkpoint.iterdir():
        shutil.copy(path, tmp_path / path.name)
    before = files_of(tmp_path)
    monkeypatch.setattr(*writer)
    with pytest.raises(SimulatedKill):
        if save == "model":
            model.save(tmp_path / "model.zip")
        else:
            model.save_replay_buffer(tmp_path / "buffer.pkl")
    monkeypatch.undo()
    # Every file is the previous complete one, and no partial file is left under any name.
    assert files_of(tmp_path) == before


def test_a_checkpoint_callback_writes_no_temporary_files(tmp_path):
    from stable_baselines3.common.callbacks import CheckpointCallback

    model = tiny_model(DIPPER, short_maze())
    model.learn(40, callback=CheckpointCallback(save_freq=20, save_path=str(tmp_path), save_replay_buffer=True))
    names = sorted(path.name for path in tmp_path.iterdir())
    assert names == [
        "rl_model_20_steps.zip",
        "rl_model_40_steps.zip",
        "rl_model_replay_buffer_20_steps.high.npz",
        "rl_model_replay_buffer_20_steps.pkl",
        "rl_model_replay_buffer_40_steps.high.npz",
        "rl_model_replay_buffer_40_steps.pkl",
    ]


def buffers_of(model):
    state = [model.lower.replay_buffer, model.lower.replay_buffer.pos]
    if isinstance(model, DIPPER):
        state += [model.preferences, len(model.preferences), model.trajectory_buffer.lengths.copy()]
    else:
        state += [model.higher.replay_buffer]
    return state


def same_buffers(first, second):
    return all(
        np.array_equal(a, b) if isinstance(a, np.ndarray) else a is b or a == b for a, b in zip(first, second, strict=True)
    )


@pytest.mark.parametrize(
    "model_class, damaged, damage, error",
    [
        (DIPPER, "buffer.high.npz", "delete", FileNotFoundError),
        (DIPPER, "buffer.high.npz", "truncate", ValueError),
        (DIPPER, "buffer.pkl", "truncate", ValueError),
        (HIER, "buffer.higher.pkl", "delete", FileNotFoundError),
        (HIER, "buffer.higher.pkl", "truncate", ValueError),
    ],
)
def test_a_failed_buffer_load_changes_nothing_and_names_the_file(trained, tmp_path, model_class, damaged, damage, error):
    model, checkpoint = trained[model_class]
    for path in checkpoint.iterdir():
        shutil.copy(path, tmp_path / path.name)
    if damage == "delete":
        (tmp_path / damaged).unlink()
    else:
        truncate(tmp_path / damaged)
    before = buffers_of(model)
    with pytest.raises(error, match=damaged):
        model.load_replay_buffer(tmp_path / "buffer.pkl")
    assert same_buffers(buffers_of(model), before)
    # The undamaged checkpoint still loads.
    model.load_replay_buffer(checkpoint / "buffer.pkl")
    assert model.lower.replay_buffer is not before[0] and model.lower.replay_buffer.pos == before[1]


def test_a_replay_buffer_of_another_algorithm_is_refused_before_anything_changes(trained, tmp_path):
    dipper_checkpoint, hier_checkpoint = trained[DIPPER][1], trained[HIER][1]
    shutil.copy(dipper_checkpoint / "buffer.pkl", tmp_path / "buffer.pkl")
    shutil.copy(hier_checkpoint / "buffer.higher.pkl", tmp_path / "buffer.higher.pkl")
    piper = tiny_model(PIPER, short_maze())
    before = piper.higher.replay_buffer
    with pytest.raises(ValueError, match=r"buffer\.higher\.pkl.*HerReplayBuffer"):
        piper.load_replay_buffer(tmp_path / "buffer.pkl")
    assert piper.higher.replay_buffer is before


# ---------------------------------------------------------------------------------------------------- streams


@pytest.mark.parametrize("model_class", [DIPPER, HIER, DAC, DPOFlat])
def test_streams_are_refused_where_a_checkpoint_has_several_files(model_class, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    model = any_tiny_model(model_class, short_maze())
    with pytest.raises(TypeError, match="needs a file path"):
        model.save_replay_buffer(io.BytesIO())
    with pytest.raises(TypeError, match="needs a file path"):
        model.load_replay_buffer(io.BytesIO())
    assert list(tmp_path.iterdir()) == []  # nothing written under the stream's repr


@pytest.mark.parametrize("model_class, kwargs", [(RAPS, {}), (DAC, {"absorbing_states": False})])
def test_a_single_file_checkpoint_round_trips_through_a_stream(model_class, kwargs):
    model = any_tiny_model(model_class, short_maze(), **kwargs)
    model.learn(40)
    stream = io.BytesIO()
    model.save_replay_buffer(stream)
    resumed = any_tiny_model(model_class, short_maze(), **kwargs)
    stream.seek(0)
    resumed.load_replay_buffer(stream)
    assert resumed.replay_buffer.pos == model.replay_buffer.pos > 0
    np.testing.assert_array_equal(resumed.replay_buffer.actions, model.replay_buffer.actions)


@pytest.mark.parametrize("model_class", [DIPPER, HIER, PIPER, SAGA, HAC, RAPS, DAC, DPOFlat, SACDemo])
def test_a_model_file_with_nan_weights_is_refused_at_load_naming_the_tensor(model_class, tmp_path):
    """Saved after its training diverged, a model failed only at its first prediction, inside torch's Normal."""
    model = any_tiny_model(model_class, short_maze())
    name, weight = next(iter(model.policy.named_parameters()))
    with th.no_grad():
        weight.view(-1)[0] = float("nan")
    model.save(tmp_path / "model.zip")
    path = re.escape(str(tmp_path / "model.zip"))
    with pytest.raises(ValueError, match=rf"{path} holds NaN or infinite values in \S*policy\.{re.escape(name)}: .*earlier"):
        model_class.load(tmp_path / "model.zip")


def test_an_infinite_torch_variable_is_named_too(tmp_path):
    model = tiny_model(DIPPER, short_maze())
    with th.no_grad():
        model.lower.log_ent_coef.fill_(float("inf"))
    model.save(tmp_path / "model.zip")
    with pytest.raises(ValueError, match=r"holds NaN or infinite values in lower\.log_ent_coef: "):
        DIPPER.load(tmp_path / "model.zip", env=short_maze())


# ---------------------------------------------------------------------------------------------------- demonstrations


@pytest.fixture(scope="module")
def maze_demos(tmp_path_factory):
    path = tmp_path_factory.mktemp("demos") / "maze.npz"
    expert_demonstrations(MAZE, n_episodes=2, seed=0).save(path)
    return path


def other_env_demos(maze_demos, path, part):
    demos = load_demonstrations(maze_demos)
    if part == "observation":
        for group in (demos.observations, demos.next_observations):
            group["observation"] = np.concatenate([group["observation"], group["observation"]], axis=1)
    else:
        demos.actions = np.zeros((len(demos), 4), np.float32)
    demos.env_id = "FetchPush-v4"
    demos.save(path)
    return path


def demonstrations(model_class, **settings):
    """The keywords that give ``model_class`` demonstrations: DAC's own, the others' demo_kwargs."""
    return settings if model_class is DAC else dict(demo_kwargs=settings)


@pytest.mark.parametrize("model_class", [DIPPER, HIER, PIPER, SAGA, HAC, DAC, SACDemo])
@pytest.mark.parametrize("part", ["observation", "actions"])
def test_demonstrations_of_another_env_are_refused_at_construction(model_class, part, maze_demos, tmp_path):
    path = other_env_demos(maze_demos, tmp_path / "push.npz", part)
    with pytest.raises(ValueError, match=f"{part}.*shape.*{re.escape(str(path))}.*recorded on another env.*FetchPush-v4"):
        any_tiny_model(model_class, short_maze(), **demonstrations(model_class, demo_path=str(path)))


@pytest.mark.parametrize("model_class", [HIER, DAC, SACDemo])
@pytest.mark.parametrize("n_demos", [0, 3])
def test_n_demos_must_be_between_one_and_the_episodes_in_the_file(model_class, n_demos, maze_demos):
    message = (
        "n_demos" if n_demos == 0 else rf"holds 2 episodes \({re.escape(str(maze_demos))}\): choose n_demos between 1 and 2"
    )
    with pytest.raises(ValueError, match=message):
        any_tiny_model(model_class, short_maze(), **demonstrations(model_class, demo_path=str(maze_demos), n_demos=n_demos))


@pytest.mark.parametrize(
    "damage, message",
    [
        (truncate, "not a complete npz archive"),
        (lambda path: path.write_text("observation,action\n0,1\n"), r"not an npz archive \(it starts with b'obse'\)"),
        (lambda path: path.write_bytes(b""), r"not an npz archive \(it is empty\)"),
    ],
    ids=["truncated", "csv", "empty"],
)
def test_unreadable_demonstration_files_are_named(damage, message, maze_demos, tmp_path):
    path = tmp_path / "demos.npz"
    shutil.copy(maze_demos, path)
    damage(path)
    with pytest.raises(ValueError, match=f"Malformed demonstration file {re.escape(str(path))}: {message}") as error:
        load_demonstrations(path)
    assert "allow_pickle" not in str(error.value)
    with pytest.raises(FileNotFoundError, match=re.escape(str(tmp_path / "missing.npz"))):
        load_demonstrations(tmp_path / "missing.npz")


def test_a_damaged_cached_default_demonstration_says_which_file_to_delete(tmp_path, monkeypatch, maze_demos):
    monkeypatch.setenv("SB3_DIPPER_CACHE", str(tmp_path))
    cached = default_demonstration_path(MAZE)
    cached.parent.mkdir(parents=True)
    shutil.copy(maze_demos, cached)
    truncate(cached)
    with pytest.raises(ValueError, match=f"delete {re.escape(str(cached))}"):
        default_demonstrations(MAZE)
    cached.unlink()
    assert default_demonstrations(MAZE).n_episodes == 1  # made again
    assert [path.name for path in cached.parent.iterdir()] == [cached.name]


def rewrite_npz(path, change):
    """Rewrite the npz file at ``path`` as a valid archive, each array passed through ``change(key, array)``."""
    with np.load(path) as data:
        arrays = {key: change(key, data[key]) for key in data.files}
    np.savez(path, **arrays)


@pytest.mark.parametrize("factor", [50.0, -1.0])
def test_a_cached_default_demonstration_changed_since_it_was_written_is_refused(tmp_path, monkeypatch, factor):
    """The reported case: the cache rewritten as a valid npz with its actions scaled by 50 (or negated) was cloned."""
    monkeypatch.setenv("SB3_DIPPER_CACHE", str(tmp_path))
    made = default_demonstrations(MAZE)
    cached = default_demonstration_path(MAZE)
    rewrite_npz(cached, lambda key, array: array * factor if key == "actions" else array)
    with pytest.raises(ValueError, match=rf"{re.escape(str(cached))}: its content does not match the digest .* delete"):
        default_demonstrations(MAZE)
    cached.unlink()
    np.testing.assert_array_equal(default_demonstrations(MAZE).actions, made.actions)  # made again


def test_a_cache_written_before_digests_is_made_again_with_a_warning(tmp_path, monkeypatch):
    monkeypatch.setenv("SB3_DIPPER_CACHE", str(tmp_path))
    made = default_demonstrations(MAZE)
    cached = default_demonstration_path(MAZE)
    with np.load(cached) as data:
        assert "sha256" in data.files
    # Scaled and without a digest: a cache of an earlier version cannot be told from a changed one, so it is replaced.
    with np.load(cached) as data:
        old = {key: data[key] * 50.0 if key == "actions" else data[key] for key in data.files if key != "sha256"}
    np.savez(cached, **old)
    with pytest.warns(UserWarning, match=rf"{re.escape(str(cached))} was cached before .* made again"):
        again = default_demonstrations(MAZE)
    np.testing.assert_array_equal(again.actions, made.actions)
    with np.load(cached) as data:
        assert "sha256" in data.files


# ---------------------------------------------------------------------------------------------------- preference files

OBS_SPACE = spaces.Dict(
    {
        "observation": spaces.Box(-10, 10, (4,), np.float32),
        "achieved_goal": spaces.Box(-10, 10, (2,), np.float32),
        "desired_goal": spaces.Box(-10, 10, (2,), np.float32),
    }
)


def labelled_pairs(n_pairs, horizon=3):
    rng = np.random.default_rng(0)

    def steps(size):
        return rng.normal(size=(2, n_pairs, horizon, size)).astype(np.float32)

    return TrajectoryPairs(
        observations={key: steps(space.shape[0]) for key, space in OBS_SPACE.spaces.items()},
        actions=steps(2),
        reached_actions=steps(2),
        next_achieved_goals=steps(2),
        mask=np.ones((2, n_pairs, horizon), bool),
        labels=rng.choice([0.0, 0.5, 1.0], size=n_pairs).astype(np.float32),
    )


def preference_file(path, n_pairs=4, corrupt=None):
    dataset = PreferenceDataset(capacity=n_pairs)
    dataset.add(labelled_pairs(n_pairs))
    arrays = dataset.to_arrays()
    if corrupt is not None:
        corrupt(arrays)
    np.savez(path, **arrays)
    return path


MODEL_SHAPES = PairShapes(
    observations={"observation": (4,), "achieved_goal": (2,), "desired_goal": (2,)}, action_dim=2, length=3
)


@pytest.mark.parametrize(
    "corrupt, message",
    [
        (lambda arrays: arrays.pop("observations/observation"), r"missing \['observations/observation'\]"),
        (lambda arrays: arrays["actions"].__setitem__((0, 0, 0, 0), np.nan), "actions holds NaN"),
        (lambda arrays: arrays["labels"].__setitem__(0, np.nan), "labels holds NaN"),
        (lambda arrays: arrays.update(mask=np.full((2, 4, 3), 2)), "mask must hold booleans"),
        (
            lambda arrays: arrays.update(next_achieved_goals=np.zeros((2, 4, 3, 3), np.float32)),
            r"next_achieved_goals must have shape \(2, 4, 3, 2\)",
        ),
    ],
    ids=["missing-key", "nan-action", "nan-label", "mask", "goal-size"],
)
def test_malformed_preference_files_are_refused(corrupt, message, tmp_path):
    path = preference_file(tmp_path / "prefs.npz", corrupt=corrupt)
    with pytest.raises(ValueError, match=f"Malformed preference file {re.escape(str(path))}: {message}"):
        PreferenceDataset.load(path)


@pytest.mark.parametrize(
    "shapes, message",
    [
        (PairShapes({**MODEL_SHAPES.observations, "observation": (6,)}, 2, 3), r"observations/observation must have shape"),
        (PairShapes(MODEL_SHAPES.observations, 3, 3), r"actions must have shape \(2, 4, 3, 3\)"),
        (PairShapes({**MODEL_SHAPES.observations, "absorbing": (1,)}, 2, 3), "missing"),
        (PairShapes(MODEL_SHAPES.observations, 2, 5), "T=3 steps, the model's have 5"),
    ],
    ids=["observation-size", "action-size", "key", "length"],
)
def test_preference_files_are_checked_against_the_model(shapes, message, tmp_path):
    path = preference_file(tmp_path / "prefs.npz")
    assert len(PreferenceDataset.load(path, shapes=MODEL_SHAPES)) == 4
    with pytest.raises(ValueError, match=message):
        PreferenceDataset.load(path, shapes=shapes)


def test_pairs_beyond_the_capacity_are_dropped_with_a_warning(tmp_path):
    path = preference_file(tmp_path / "prefs.npz", n_pairs=200)
    with pytest.warns(UserWarning, match="kept the first 3 and dropped 197. Raise capacity"):
        assert len(PreferenceDataset.load(path, capacity=3)) == 3
    buffer = TrajectoryBuffer(capacity=4, max_length=3, observation_space=OBS_SPACE, action_dim=2)
    dataset = PreferenceDataset(200)
    dataset.add(labelled_pairs(200))
    save_preference_data(tmp_path / "checkpoint.high.npz", buffer, dataset)
    with pytest.warns(UserWarning, match="dropped 197. Raise n_preference_pairs to 200"):
        assert len(load_preference_data(tmp_path / "checkpoint.high.npz", buffer, label_budget=3)) == 3


def test_a_checkpoint_of_another_env_leaves_the_trajectory_buffer_unchanged(tmp_path):
    saved = TrajectoryBuffer(capacity=4, max_length=3, observation_space=OBS_SPACE, action_dim=2)
    dataset = PreferenceDataset(4)
    dataset.add(labelled_pairs(4))
    save_preference_data(tmp_path / "checkpoint.high.npz", saved, dataset)
    other_space = spaces.Dict({**OBS_SPACE.spaces, "observation": spaces.Box(-10, 10, (6,), np.float32)})
    other = TrajectoryBuffer(capacity=4, max_length=3, observation_space=other_space, action_dim=2)
    other.lengths[:] = 2
    with pytest.raises(ValueError, match="trajectories/observations/observation has shape"):
        load_preference_data(tmp_path / "checkpoint.high.npz", other, label_budget=4)
    assert (other.lengths == 2).all()
    smaller = TrajectoryBuffer(capacity=2, max_length=3, observation_space=OBS_SPACE, action_dim=2)
    with pytest.raises(ValueError, match="trajectory_buffer_size=4"):
        load_preference_data(tmp_path / "checkpoint.high.npz", smaller, label_budget=4)
