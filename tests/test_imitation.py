"""Demonstrations (npz round trip, malformed files) and the lower level's Q-filtered behaviour cloning."""

import re
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

from sb3_dipper import DIPPER, HIER
from sb3_dipper.common import imitation
from sb3_dipper.common.demonstrations import (
    DART_ACTION_NOISE,
    demonstrations_for,
    load_demonstrations,
    normalize_like_demonstrations,
)
from sb3_dipper.common.imitation import DEFAULT_DEMO_KWARGS, DemonstrationBuffer, behaviour_cloning_loss, q_filter_mask
from sb3_dipper.common.low_level import clipped_soft_target
from sb3_dipper.common.subgoals import SubgoalSpace
from sb3_dipper.envs.demos import expert_demonstrations
from tests.conftest import HIERARCHICAL_ALGORITHMS, saved_in_old_form, short_maze, tiny_model


@pytest.fixture(scope="module")
def maze_demos(tmp_path_factory):
    path = tmp_path_factory.mktemp("demos") / "maze.npz"
    expert_demonstrations("PointMazeFourRooms-v0", n_episodes=2, seed=0).save(path)
    return path


def test_demonstrations_round_trip(maze_demos):
    demos = load_demonstrations(maze_demos)
    assert demos.n_episodes == 2 and len(demos) == 400 and demos.env_id == "PointMazeFourRooms-v0"
    assert demos.successes[199] == 1.0 and demos.successes[-1] == 1.0
    np.testing.assert_allclose(demos.next_observations["observation"][:-1][:199], demos.observations["observation"][1:200])
    one = load_demonstrations(maze_demos, n_episodes=1)
    assert one.n_episodes == 1 and len(one) == 200
    with pytest.raises(ValueError, match="holds 2 episodes"):
        load_demonstrations(maze_demos, n_episodes=3)


@pytest.mark.parametrize(
    "corrupt, message",
    [
        (lambda arrays: arrays.pop("actions"), "missing"),
        (lambda arrays: arrays.update(episode_lengths=np.array([150, 150])), "sum to 400"),
        (lambda arrays: arrays.update(rewards=np.zeros(10)), "rewards has 10 rows"),
        (lambda arrays: arrays["actions"].__setitem__((3, 0), np.nan), "NaN"),
    ],
)
def test_malformed_demonstration_files_give_a_clear_error(maze_demos, tmp_path, corrupt, message):
    with np.load(maze_demos) as data:
        arrays = {key: data[key] for key in data.files}
    corrupt(arrays)
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ValueError, match=f"Malformed demonstration file.*{message}"):
        load_demonstrations(tmp_path / "bad.npz")


def test_a_minari_dataset_directory_is_read(maze_demos, tmp_path):
    minari_storage = pytest.importorskip("minari.dataset.minari_storage")
    from minari.data_collector.episode_buffer import EpisodeBuffer

    demos = load_demonstrations(maze_demos)
    env = short_maze().envs[0]
    storage = minari_storage.MinariStorage.new(tmp_path / "data", env.observation_space, env.action_space, data_format="hdf5")
    episodes = []
    for start, length in zip(demos.episode_starts, demos.episode_lengths, strict=True):
        steps = slice(start, start + length)
        observations = {
            key: np.concatenate([demos.observations[key][steps], demos.next_observations[key][start + length - 1][None]])
            for key in demos.observations
        }
        episodes.append(
            EpisodeBuffer(
                observations=observations,
                actions=demos.actions[steps],
                rewards=list(demos.rewards[steps]),
                terminations=[False] * int(length),
                truncations=[False] * (int(length) - 1) + [True],
                infos={"is_success": demos.successes[steps]},
            )
        )
    storage.update_episodes(episodes)
    storage.update_metadata(
        {"dataset_id": "sb3-dipper/maze-demos-v0", "minari_version": pytest.importorskip("minari").__version__}
    )
    loaded = load_demonstrations(tmp_path)
    assert loaded.n_episodes == 2
    np.testing.assert_allclose(loaded.actions, demos.actions)
    np.testing.assert_allclose(loaded.next_observations["achieved_goal"], demos.next_observations["achieved_goal"])
    np.testing.assert_array_equal(loaded.successes, demos.successes)


def test_demo_subgoals_are_later_achieved_subgoals_or_the_demos_own_goal(maze_demos):
    """PIPER's rule: 80 % a later achieved subgoal of the same episode (however far), 20 % the demonstration's goal."""
    demos = load_demonstrations(maze_demos)
    space = SubgoalSpace(np.full(2, -3.5), np.full(2, 3.5), threshold=0.45)
    buffer = DemonstrationBuffer(demos, space, scaled_actions=demos.actions)
    np.random.seed(0)
    observations, _, next_observations, rewards = buffer.sample(2000)
    relabelled, far = 0, 0
    for row in range(2000):
        step = int(np.flatnonzero(np.all(buffer.observation == observations["observation"][row], axis=1))[0])
        later = buffer.next_achieved[step : buffer.last_step[step] + 1]
        goal = observations["desired_goal"][row]
        is_later = bool(np.any(np.all(later == goal, axis=1)))
        assert is_later or np.array_equal(goal, buffer.desired[step])
        relabelled += is_later
        far += is_later and not np.any(np.all(later[:5] == goal, axis=1))
    assert relabelled / 2000 == pytest.approx(0.8, abs=0.04)
    assert far > 0  # beyond the next K = 5 steps: the old within-option rule never drew these
    distance = np.linalg.norm(next_observations["achieved_goal"] - observations["desired_goal"], axis=1)
    np.testing.assert_array_equal(rewards, -(distance > 0.45).astype(np.float32))
    np.testing.assert_array_equal(next_observations["desired_goal"], observations["desired_goal"])


def test_behaviour_cloning_loss_by_hand():
    policy = th.tensor([[0.0, 0.5], [1.0, 1.0], [0.2, -0.2]])
    demo = th.tensor([[1.0, 0.5], [0.0, 0.0], [0.2, 0.0]])
    # Squared errors per row: 1.0, 2.0, 0.04; the filter keeps rows 0 and 2: 1.04.
    assert behaviour_cloning_loss(policy, demo, th.tensor([1.0, 0.0, 1.0])).item() == pytest.approx(1.04)


class FixedCritic:
    """Q_1(s, a) = a[0]: the first action component is all the critic cares about."""

    def q1_forward(self, observations, actions):
        return actions[:, :1]


def test_q_filter_keeps_demo_actions_the_critic_prefers():
    demo = th.tensor([[0.9, 0.0], [0.1, 0.0], [0.5, 0.0]])
    policy = th.tensor([[0.5, 0.0], [0.5, 0.0], [0.5, 0.0]])
    np.testing.assert_array_equal(q_filter_mask(FixedCritic(), {}, demo, policy).numpy(), [1.0, 0.0, 0.0])


@pytest.mark.parametrize("model_class", [DIPPER, HIER])
def test_lower_level_clones_demonstrations(model_class, maze_demos, tmp_path):
    from stable_baselines3.common.logger import configure

    model = tiny_model(model_class, short_maze(), demo_kwargs=dict(demo_path=str(maze_demos), n_demos=1, demo_share=0.25))
    assert len(model.lower.demonstrations) == 200
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(200, log_interval=1)
    header = open(tmp_path / "progress.csv").readline().strip().split(",")
    assert {"train/low_bc_loss", "train/low_q_filter_kept"} <= set(header)


def test_normalize_like_demonstrations_scales_by_the_demonstrations_states(maze_demos):
    """Mean and std + 0.01 of the demonstrated states, hand-computed on two states, and frozen."""
    demonstrations = load_demonstrations(maze_demos).first_episodes(1)
    observation = demonstrations.observations["observation"]
    observation[:] = 0.0
    observation[: len(observation) // 2, 0] = 2.0  # first input: half 2, half 0 -> mean 1, std 1
    env = VecNormalize(short_maze(), norm_reward=False)
    normalize_like_demonstrations(env, demonstrations)
    assert not env.training
    scaled = env.normalize_obs({key: value[:1] for key, value in demonstrations.observations.items()})["observation"]
    np.testing.assert_allclose(scaled[0], [1 / 1.01, 0.0, 0.0, 0.0], rtol=1e-6)
    env.reset()
    env.step(np.zeros((1, 2)))
    np.testing.assert_allclose(env.obs_rms["observation"].mean, [1.0, 0.0, 0.0, 0.0])


@pytest.mark.parametrize("model_class", HIERARCHICAL_ALGORITHMS)
def test_normalize_from_demos_keeps_the_demonstrations_statistics(model_class, maze_demos, tmp_path):
    """Through training, into both levels' inputs, and again for the env a saved model is loaded with or moved to."""
    demonstrations = load_demonstrations(maze_demos).first_episodes(2)
    expected_mean = demonstrations.observations["observation"].astype(np.float64).mean(0)
    env = VecNormalize(short_maze(), norm_reward=False)
    demo_kwargs = dict(demo_path=str(maze_demos), n_demos=2, normalize_from_demos=True)
    model = tiny_model(model_class, env, demo_kwargs=demo_kwargs)
    model.learn(100)
    np.testing.assert_allclose(env.obs_rms["observation"].mean, expected_mean)
    np.testing.assert_allclose(model.low_normalizer.statistics["observation"][0], expected_mean)
    model.save(tmp_path / "model.zip")
    fresh = VecNormalize(short_maze(seed=3), norm_reward=False)
    loaded = model_class.load(tmp_path / "model.zip", env=fresh)
    np.testing.assert_allclose(fresh.obs_rms["observation"].mean, expected_mean)
    assert not fresh.training and loaded.demo_kwargs == {**DEFAULT_DEMO_KWARGS, **demo_kwargs}
    another = VecNormalize(short_maze(seed=5), norm_reward=False)
    model.set_env(another)
    np.testing.assert_allclose(another.obs_rms["observation"].mean, expected_mean)


def test_a_demo_path_given_as_a_pathlib_path_is_kept_as_its_string(maze_demos, maze_env, tmp_path):
    model = tiny_model(HIER, maze_env, demo_kwargs=dict(demo_path=maze_demos, n_demos=2))
    assert model.demo_kwargs["demo_path"] == str(maze_demos)
    model.learn(60)
    model.save(tmp_path / "model")
    assert HIER.load(tmp_path / "model").demo_kwargs["demo_path"] == str(maze_demos)


def test_normalize_from_demos_needs_demonstrations_and_vec_normalize(maze_demos, maze_env):
    needs_demos = r"demo_kwargs\['normalize_from_demos'\]=True .* give demo_kwargs\['demo_path'\] too"
    with pytest.raises(ValueError, match=needs_demos):
        tiny_model(DIPPER, VecNormalize(short_maze()), demo_kwargs=dict(normalize_from_demos=True))
    unwrapped = r"demo_kwargs\['normalize_from_demos'\]=True .* not wrapped in VecNormalize\(norm_obs=True\)"
    demo_kwargs = dict(demo_path=str(maze_demos), normalize_from_demos=True)
    with pytest.raises(ValueError, match=unwrapped):
        tiny_model(DIPPER, maze_env, demo_kwargs=demo_kwargs)
    env = VecNormalize(short_maze(), norm_reward=False)
    model = tiny_model(DIPPER, env, demo_kwargs=demo_kwargs)
    with pytest.raises(ValueError, match=unwrapped):
        model.set_env(maze_env)
    assert model.env is env, "a refused env leaves the model as it was"


def test_default_demonstration_is_made_once_and_deterministic(tmp_path, monkeypatch):
    from sb3_dipper.envs.demos import default_demonstration_path, default_demonstrations

    monkeypatch.setenv("SB3_DIPPER_CACHE", str(tmp_path))
    first = default_demonstrations("PointMazeFourRooms-v0")
    assert default_demonstration_path("PointMazeFourRooms-v0").exists() and first.n_episodes == 1
    fresh = expert_demonstrations("PointMazeFourRooms-v0", n_episodes=1, seed=0)
    np.testing.assert_array_equal(first.actions, fresh.actions)


def test_auto_dart_demonstrations_are_the_experts_noisy_episodes_cached_apart(tmp_path, monkeypatch):
    """demo_path="auto:dart<N>" gives what ``sb3-dipper-demos --n-episodes N --action-noise 0.1`` writes, cached beside
    (not over) the single default demonstration, and builds a model that clones them."""
    from sb3_dipper.envs.demos import default_demonstration_path

    monkeypatch.setenv("SB3_DIPPER_CACHE", str(tmp_path))
    env = short_maze()
    dart = demonstrations_for("auto:dart3", env)
    written = expert_demonstrations("PointMazeFourRooms-v0", n_episodes=3, seed=0, action_noise=DART_ACTION_NOISE)
    assert dart.n_episodes == 3
    np.testing.assert_array_equal(dart.actions, written.actions)
    np.testing.assert_array_equal(dart.observations["observation"], written.observations["observation"])
    assert default_demonstration_path("PointMazeFourRooms-v0", 3, DART_ACTION_NOISE).exists()
    assert not default_demonstration_path("PointMazeFourRooms-v0").exists()
    single = demonstrations_for("auto", env)
    assert single.n_episodes == 1 and not np.array_equal(single.actions, dart.first_episodes(1).actions)
    model = tiny_model(DIPPER, env, demo_kwargs=dict(demo_path="auto:dart3", n_demos=3))
    assert model.lower.demonstrations is not None and len(model.lower.demonstrations) == len(dart)


def test_auto_dart_without_n_demos_clones_all_its_episodes(tmp_path, monkeypatch):
    """The reported case: 'auto:dart20' without n_demos made and cached 20 episodes and cloned one."""
    monkeypatch.setenv("SB3_DIPPER_CACHE", str(tmp_path))
    env = short_maze()
    all_three = tiny_model(DIPPER, env, demo_kwargs=dict(demo_path="auto:dart3")).lower.demonstrations
    assert all_three is not None and len(np.unique(all_three.last_step)) == 3
    assert len(all_three) == len(demonstrations_for("auto:dart3", env))
    two = tiny_model(HIER, env, demo_kwargs=dict(demo_path="auto:dart3", n_demos=2)).lower.demonstrations
    assert two is not None and len(np.unique(two.last_step)) == 2
    message = r"n_demos=4 asks for more episodes than demo_path='auto:dart3' makes \(3\): for more, use demo_path='auto:dart4'"
    with pytest.raises(ValueError, match=message + r".*at most n_demos=3 \(leaving n_demos out uses all 3\)"):
        tiny_model(DIPPER, env, demo_kwargs=dict(demo_path="auto:dart3", n_demos=4))
    with pytest.raises(ValueError, match=r"n_demos=2 asks for more episodes than demo_path='auto' makes \(1\)"):
        tiny_model(HIER, env, demo_kwargs=dict(demo_path="auto", n_demos=2))


@pytest.mark.parametrize("spec", ["auto:dart0", "auto:dart", "auto:20", "auto:dart-5"])
def test_malformed_auto_demonstration_specs_say_what_is_accepted(spec):
    with pytest.raises(ValueError, match=r"demo_path='auto:.*'auto' \(one episode\) or 'auto:dart<N>'"):
        tiny_model(DIPPER, short_maze(), demo_kwargs=dict(demo_path=spec))


class _LineEnv(gym.Env):
    """A goal env on a line whose next position is the position plus the executed action: it shows what was executed."""

    observation_space = gym.spaces.Dict(
        {key: gym.spaces.Box(-10.0, 10.0, (1,)) for key in ("observation", "achieved_goal", "desired_goal")}
    )
    action_space = gym.spaces.Box(-1.0, 1.0, (1,))

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.position, self.steps = np.zeros(1, dtype=np.float32), 0
        return self._observation(), {}

    def step(self, action):
        self.position, self.steps = self.position + action, self.steps + 1
        return self._observation(), 0.0, False, self.steps == 8, {"is_success": 1.0}

    def _observation(self):
        goal = np.ones(1, dtype=np.float32)
        return {"observation": self.position.copy(), "achieved_goal": self.position.copy(), "desired_goal": goal}


class _HalfStepExpert:
    def __init__(self, env):
        pass

    def reset(self):
        pass

    def act(self, observation):
        return np.array([0.5], dtype=np.float32)


@pytest.fixture
def line_env_id():
    gym.register("DartLine-v0", entry_point=_LineEnv)
    yield "DartLine-v0"
    del gym.registry["DartLine-v0"]


def test_dart_demonstrations_record_the_experts_action_and_execute_a_noisy_one(line_env_id):
    from sb3_dipper.common.demonstrations import collect_demonstrations

    clean = collect_demonstrations(line_env_id, _HalfStepExpert, n_episodes=2)
    executed = clean.next_observations["observation"] - clean.observations["observation"]
    np.testing.assert_allclose(executed, clean.actions, atol=1e-6)
    noisy = collect_demonstrations(line_env_id, _HalfStepExpert, n_episodes=2, action_noise=0.3)
    np.testing.assert_array_equal(noisy.actions, 0.5)  # what the expert asked for, not what the env did
    executed = noisy.next_observations["observation"] - noisy.observations["observation"]
    assert np.all(np.abs(executed) <= 1.0) and 0.15 < np.std(executed) < 0.45
    assert "action noise 0.3 (DART)" in noisy.source
    again = collect_demonstrations(line_env_id, _HalfStepExpert, n_episodes=2, action_noise=0.3)
    np.testing.assert_array_equal(again.observations["observation"], noisy.observations["observation"])
    other_seed = collect_demonstrations(line_env_id, _HalfStepExpert, n_episodes=2, seed=1, action_noise=0.3)
    assert not np.array_equal(other_seed.observations["observation"], noisy.observations["observation"])
    with pytest.raises(ValueError, match=r"action_noise must be a finite standard deviation >= 0, got -0\.1"):
        collect_demonstrations(line_env_id, _HalfStepExpert, n_episodes=1, action_noise=-0.1)


def test_the_demos_command_writes_dart_episodes(tmp_path, capsys):
    from sb3_dipper.envs.demos import main

    out = tmp_path / "dart.npz"
    main(["--env", "PointMazeFourRooms-v0", "--n-episodes", "2", "--action-noise", "0.2", "--out", str(out)])
    demonstrations = load_demonstrations(out)
    assert demonstrations.n_episodes == 2 and "Wrote 2 episodes" in capsys.readouterr().out
    clean = expert_demonstrations("PointMazeFourRooms-v0", n_episodes=2)
    assert not np.array_equal(demonstrations.observations["observation"], clean.observations["observation"])
    with pytest.raises(SystemExit):
        main(["--env", "PointMazeFourRooms-v0", "--action-noise", "-1", "--out", str(out)])


@pytest.mark.parametrize("n_episodes", ["0", "-3"])
def test_the_demos_command_refuses_fewer_than_one_episode(n_episodes, tmp_path, capsys):
    """The reported case: numpy's "need at least one array to concatenate", naming neither the flag nor the fix."""
    from sb3_dipper.envs.demos import main

    with pytest.raises(SystemExit) as exited:
        main(["--env", "PointMazeFourRooms-v0", "--n-episodes", n_episodes, "--out", str(tmp_path / "demos.npz")])
    assert exited.value.code == 2
    assert f"--n-episodes must be at least 1 (the episodes to write), got {n_episodes}" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_collecting_fewer_than_one_episode_is_refused_naming_n_episodes():
    with pytest.raises(ValueError, match="n_episodes must be at least 1, got 0"):
        expert_demonstrations("PointMazeFourRooms-v0", n_episodes=0)


def test_the_demos_command_names_the_file_it_wrote(tmp_path, capsys):
    """--out without .npz: the file is <out>.npz (numpy's rule), and the message named <out>, which does not exist."""
    from sb3_dipper.envs.demos import main

    main(["--env", "PointMazeFourRooms-v0", "--out", str(tmp_path / "mydemos")])
    assert capsys.readouterr().out.rstrip().endswith(f" to {tmp_path / 'mydemos.npz'}")
    assert [path.name for path in tmp_path.iterdir()] == ["mydemos.npz"]


def test_auto_demonstrations_name_the_tasks_that_have_one():
    """demo_path="auto" loads what the task registered (sb3_dipper.envs, one per scripted expert); elsewhere it says
    which tasks have one and what to pass instead."""
    env = DummyVecEnv([lambda: gym.make("FetchReach-v4")])
    with pytest.raises(
        ValueError, match=r"no scripted demonstrations for 'FetchReach-v4' \(tasks with them: .*PointMazeFourRooms-v0"
    ):
        demonstrations_for("auto", env)
    with pytest.raises(ValueError, match=r"demo_path='auto:dart20': no scripted demonstrations for 'FetchReach-v4'"):
        demonstrations_for("auto:dart20", env)


@pytest.mark.parametrize("with_demos", [True, False])
def test_lower_targets_are_clipped_when_bounds_are_given(with_demos, maze_demos, monkeypatch):
    """The authors' clip of every level's targets to [-1 / (1 - gamma), 0], with or without demonstrations."""
    targets = []

    def recording_target(*args):
        target = clipped_soft_target(*args)
        targets.append((args[-1], target.detach()))
        return target

    monkeypatch.setattr(imitation, "clipped_soft_target", recording_target)
    demo_kwargs = dict(demo_path=str(maze_demos)) if with_demos else {}
    model = tiny_model(DIPPER, short_maze(), low_level_kwargs=dict(target_q_bounds=(-2.0, 0.0)), demo_kwargs=demo_kwargs)
    model.learn(120)
    assert targets, "the clipped update ran"
    for bounds, target in targets:
        assert bounds == (-2.0, 0.0) and target.min() >= -2.0 and target.max() <= 0.0


def test_bad_target_bounds_are_refused(maze_env):
    with pytest.raises(ValueError, match="target_q_bounds must be"):
        tiny_model(DIPPER, maze_env, low_level_kwargs=dict(target_q_bounds=(0.0, -1.0)))


# ------------------------------------------------------------------------------- demo_kwargs, and the form before it


def test_the_demo_settings_before_demo_kwargs_still_work_and_warn(maze_demos, tmp_path):
    """Given to the constructor and to load, read and set as attributes, and in a file saved before demo_kwargs."""
    old_form = dict(demo_path=str(maze_demos), n_demos=2, q_filter=False, bc_coef=0.5)
    message = (
        "HIER's demo_path, n_demos, bc_coef, q_filter are deprecated: pass demo_kwargs={'demo_path': "
        f"{str(maze_demos)!r}, 'n_demos': 2, 'bc_coef': 0.5, 'q_filter': False}} instead"
    )
    with pytest.warns(DeprecationWarning, match=re.escape(message)):
        model = tiny_model(HIER, short_maze(), demo_kwargs=dict(bc_coef=0.1, demo_share=0.25), **old_form)
    expected = {**DEFAULT_DEMO_KWARGS, **old_form, "demo_share": 0.25}  # a deprecated name wins over its key
    assert model.demo_kwargs == expected and model.lower.bc_coef == 0.5 and len(model.lower.demonstrations) == 400
    with pytest.warns(DeprecationWarning, match=r"HIER.bc_coef is deprecated: use model.demo_kwargs\['bc_coef'\]"):
        assert model.bc_coef == 0.5
    with pytest.warns(DeprecationWarning, match="HIER.rl_coef is deprecated"):
        model.rl_coef = 0.01
    assert model.demo_kwargs["rl_coef"] == 0.01
    model.save(tmp_path / "new.zip")

    # The file as HIER wrote it before demo_kwargs: each setting an attribute of its own.
    saved_in_old_form(tmp_path / "new.zip", tmp_path / "old.zip", "demo_kwargs")
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)  # loading an old file is no deprecated use
        loaded = HIER.load(tmp_path / "old.zip", env=short_maze())
    assert loaded.demo_kwargs == {**expected, "rl_coef": 0.01} and not set(DEFAULT_DEMO_KWARGS) & set(vars(loaded))
    assert len(loaded.lower.demonstrations) == 400
    # A deprecated name given to load changes its key only, over the file's settings in either form.
    for path in ("old.zip", "new.zip"):
        with pytest.warns(DeprecationWarning, match=r"pass demo_kwargs=\{'demo_share': 0.5\} instead"):
            reloaded = HIER.load(tmp_path / path, env=short_maze(), demo_share=0.5)
        assert reloaded.demo_kwargs == {**expected, "rl_coef": 0.01, "demo_share": 0.5}, path
