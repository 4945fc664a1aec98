"""SB3's contracts, kept by every algorithm: load -> set_env -> learn, rollout callbacks, resuming after a callback
stopped training, the saved state a resumed run needs, time limits and classes of saved files, tensorboard, warnings,
and running both levels of a hierarchy without the algorithm (``export_policy``)."""

import base64
import json
import pickle
import re
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch as th
from sb3_contrib import TQC
from stable_baselines3 import PPO, SAC
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecNormalize

from sb3_dipper import DAC, DIPPER, HIER, RAPS, SACDemo
from sb3_dipper.common.hierarchical_policy import HierarchicalPolicy
from sb3_dipper.common.loading import _pickled_class_name
from sb3_dipper.common.low_level import SubgoalVecEnv, low_level_observation_space
from sb3_dipper.common.subgoals import SubgoalSpace, resolve_subgoal_space
from tests.conftest import (
    ALL_ALGORITHMS,
    HIERARCHICAL_ALGORITHMS,
    OPTION_ALGORITHMS,
    any_tiny_model,
    short_maze,
    tiny_model,
)
from tests.test_save_load import rollout_actions

# Algorithms that size buffers by episodes (DAC and SACDemo store transitions only).
EPISODE_SIZED_ALGORITHMS = [model_class for model_class in ALL_ALGORITHMS if model_class not in (DAC, SACDemo)]


def maze_with_time_limit(max_episode_steps: int):
    return make_vec_env(
        "sb3_dipper:PointMazeFourRooms-v0", n_envs=1, seed=1, env_kwargs={"max_episode_steps": max_episode_steps}
    )


def buffer_sizes(model) -> dict[str, int]:
    """The capacity of every buffer a model trains from."""
    sizes = {}
    for name in ("lower", "higher", ""):
        owner = getattr(model, name, None) if name else model
        buffer = getattr(owner, "replay_buffer", None)
        if buffer is not None:
            sizes[f"{name}.replay_buffer"] = buffer.buffer_size
    if hasattr(model, "trajectory_buffer"):
        sizes["trajectory_buffer"] = model.trajectory_buffer.capacity
    return sizes


def policy_parameters(model) -> dict[str, th.Tensor]:
    parameters = {f"high.{name}": tensor.clone() for name, tensor in model.policy.state_dict().items()}
    lower_policy = getattr(getattr(model, "lower", None), "policy", None)
    if lower_policy is not None:
        parameters |= {f"low.{name}": tensor.clone() for name, tensor in lower_policy.state_dict().items()}
    return parameters


# ---------------------------------------------------------------------------------------------------- load, set_env


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_load_then_set_env_then_learn_trains_with_the_configured_buffers(model_class, tmp_path, maze_env):
    model = any_tiny_model(model_class, maze_env)
    model.learn(45)
    model.save(tmp_path / "model")
    loaded = model_class.load(tmp_path / "model")
    loaded.set_env(short_maze(seed=1))
    saved, restored = policy_parameters(model), policy_parameters(loaded)
    assert saved.keys() == restored.keys() and all(th.equal(saved[name], restored[name]) for name in saved)
    if hasattr(getattr(model, "lower", None), "_n_updates"):
        assert loaded.lower._n_updates == model.lower._n_updates > 0
    loaded.learn(20, reset_num_timesteps=False)
    assert loaded.num_timesteps == 65
    assert buffer_sizes(loaded) == buffer_sizes(model)


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_set_env_moves_a_trained_model_to_the_new_env(model_class, maze_env):
    model = any_tiny_model(model_class, maze_env)
    model.learn(40)
    new_env = short_maze(seed=5)
    model.set_env(new_env)
    assert (model.option_env.venv if model_class in OPTION_ALGORITHMS else model.get_env()) is new_env
    model.learn(20, reset_num_timesteps=False)
    assert model.num_timesteps == 60


# ---------------------------------------------------------------------------------------------------- callbacks


class CountingCallback(BaseCallback):
    """Counts SB3's callback events; stops training after ``stop_at`` steps when given."""

    def __init__(self, stop_at: int | None = None) -> None:
        super().__init__()
        self.stop_at = stop_at
        self.events: list[str] = []

    def _on_rollout_start(self) -> None:
        self.events.append("start")

    def _on_step(self) -> bool:
        self.events.append("step")
        return self.stop_at is None or self.num_timesteps < self.stop_at

    def _on_rollout_end(self) -> None:
        self.events.append("end")


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_rollout_callbacks_wrap_every_rollout(model_class, maze_env):
    callback = CountingCallback()
    model = any_tiny_model(model_class, maze_env)
    model.learn(40, callback=callback)
    rollouts = "".join("(" if event == "start" else ")" if event == "end" else "." for event in callback.events)
    # Every rollout opens, takes steps and closes; an option is a rollout: K = 5 primitive steps.
    assert rollouts.count(".") == 40
    expected = "(.....)" * 8 if model_class in OPTION_ALGORITHMS else "(.)" * 40
    assert rollouts == expected


@pytest.mark.parametrize("model_class", OPTION_ALGORITHMS)
def test_a_callback_that_stops_training_skips_on_rollout_end_as_in_sb3(model_class, maze_env):
    callback = CountingCallback(stop_at=7)
    any_tiny_model(model_class, maze_env).learn(40, callback=callback)
    assert callback.events == ["start", *["step"] * 5, "end", "start", "step", "step"]


@pytest.mark.parametrize("model_class", HIERARCHICAL_ALGORITHMS)
def test_resuming_after_a_callback_stop_stores_the_true_observations_and_one_subgoal_per_her_episode(model_class, maze_env):
    model = tiny_model(model_class, maze_env)
    model.learn(40, callback=CountingCallback(stop_at=7))
    model.learn(33, reset_num_timesteps=False)
    assert model.num_timesteps == 40
    buffer = model.lower.replay_buffer
    observations, next_observations = buffer.observations["observation"][:40, 0], buffer.next_observations["observation"]
    # Two 20-step episodes: every step starts where the previous one ended, the step after the stop too.
    for step in range(1, 40):
        if step != 20:
            np.testing.assert_array_equal(observations[step], next_observations[step - 1, 0], err_msg=f"step {step}")
    # The stopped option's segment ends at the stop: every HER episode is one option, towards one subgoal.
    assert buffer.ep_length[:40, 0].max() <= model.option_steps
    assert buffer.ep_length[6, 0] == 2
    subgoals = buffer.observations["desired_goal"][:40, 0]
    for step in range(40):
        start = buffer.ep_start[step, 0]
        np.testing.assert_array_equal(subgoals[step], subgoals[start])


# ---------------------------------------------------------------------------------------------------- updates


# (n_envs, learning_starts, train_freq, gradient_steps, option_steps, total steps): the first training rounds after the
# warm-up, with a learning_starts that is not a multiple of train_freq.
WARM_UP_CASES = [(1, 29, 2, 3, 4, 36), (2, 30, 1, 2, 5, 40)]


@pytest.mark.parametrize(("n_envs", "learning_starts", "train_freq", "gradient_steps", "option_steps", "steps"), WARM_UP_CASES)
@pytest.mark.parametrize("model_class", HIERARCHICAL_ALGORITHMS)
def test_the_lower_level_owes_no_updates_for_the_warm_up_as_sb3_sac(
    model_class, n_envs, learning_starts, train_freq, gradient_steps, option_steps, steps
):
    settings = dict(learning_starts=learning_starts, train_freq=train_freq, gradient_steps=gradient_steps, batch_size=16)
    sac = SAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=n_envs), policy_kwargs=dict(net_arch=[8]), seed=0, **settings)
    sac.learn(steps)
    model = tiny_model(model_class, short_maze(n_envs=n_envs), option_steps=option_steps, **settings)
    model.learn(steps)
    assert model.num_timesteps == sac.num_timesteps == steps
    # Before, the first round also ran the warm-up's learning_starts x gradient_steps / train_freq updates at once.
    assert model.lower._n_updates == sac._n_updates > 0


# ---------------------------------------------------------------------------------------------------- saved state


def test_dipper_resumes_its_value_snapshot_and_its_schedule(tmp_path, maze_env):
    model = tiny_model(DIPPER, maze_env, value_steps=5)
    model.learn(80)
    assert model._value_snapshot_updates > 0
    model.save(tmp_path / "model")
    loaded = DIPPER.load(tmp_path / "model", env=short_maze(seed=1))
    snapshot, restored = model._value_snapshot.state_dict(), loaded._value_snapshot.state_dict()
    assert snapshot.keys() == restored.keys() and all(th.equal(snapshot[name], restored[name]) for name in snapshot)
    assert (loaded.lower._n_updates, loaded._value_snapshot_updates) == (model.lower._n_updates, model._value_snapshot_updates)


def test_a_dipper_file_without_a_value_snapshot_starts_it_from_the_lower_critic(maze_env):
    model = tiny_model(DIPPER, maze_env, value_steps=10_000)
    model.learn(45)
    assert model._value_snapshot_updates == 0 < model.lower._n_updates
    parameters = model.get_parameters()
    del parameters["_value_snapshot"]
    model.set_parameters(parameters)
    critic, snapshot = model.lower.critic.state_dict(), model._value_snapshot.state_dict()
    assert all(th.equal(critic[name], snapshot[name]) for name in critic)
    assert model._value_snapshot_updates == model.lower._n_updates


@pytest.mark.parametrize("model_class", EPISODE_SIZED_ALGORITHMS)
def test_an_env_with_another_time_limit_is_refused_unless_max_episode_steps_says_so(model_class, tmp_path, maze_env):
    model = any_tiny_model(model_class, maze_env)
    model.save(tmp_path / "model")
    with pytest.raises(ValueError, match=r"20-step episodes .*time limit is 30 steps.*max_episode_steps=30\)"):
        model_class.load(tmp_path / "model", env=maze_with_time_limit(30))
    with pytest.raises(ValueError, match=r"time limit is 30 steps.*max_episode_steps=30\)"):
        model.set_env(maze_with_time_limit(30))
    rebuilt = model_class.load(tmp_path / "model", env=maze_with_time_limit(30), max_episode_steps=30)
    assert rebuilt.max_episode_steps == 30


def umaze():
    """The small gymnasium-robotics maze: the four-room maze's spaces and time limit, a 3 x 3 subgoal box (not 7 x 7)."""
    return make_vec_env("PointMaze_UMaze-v3", n_envs=1, seed=1, env_kwargs={"max_episode_steps": 20})


SUBGOAL_BOXES = (
    r"declares the subgoal space low=\[-1.5, -1.5\], high=\[1.5, 1.5\].* model's is low=\[-3.5, -3.5\], high=\[3.5, 3.5\]"
)


@pytest.mark.parametrize("model_class", [DIPPER, HIER, RAPS])
def test_an_env_that_declares_another_subgoal_space_is_refused(model_class, tmp_path, maze_env):
    """The reported case: a four-room model loaded onto the U-maze (same spaces) trained in the four-room box."""
    model = any_tiny_model(model_class, maze_env)
    model.save(tmp_path / "model.zip")
    with pytest.raises(ValueError, match=SUBGOAL_BOXES + rf".*{model_class.__name__}\.load\(path, env=env, subgoal_space="):
        model_class.load(tmp_path / "model.zip", env=umaze())
    with pytest.raises(ValueError, match=SUBGOAL_BOXES):
        model.set_env(umaze())
    assert model.env is not None and model.get_env().envs[0].spec.id == "PointMazeFourRooms-v0"  # unchanged
    # Without an env first, the check comes with set_env.
    with pytest.raises(ValueError, match=SUBGOAL_BOXES):
        model_class.load(tmp_path / "model.zip").set_env(umaze())


def test_a_subgoal_space_chosen_by_the_user_is_kept_on_any_env(tmp_path, maze_env):
    env = umaze()
    chosen = resolve_subgoal_space(env)
    tiny_model(HIER, maze_env).save(tmp_path / "model.zip")
    loaded = HIER.load(tmp_path / "model.zip", env=env, subgoal_space=chosen)
    assert loaded.subgoal_space is chosen and not loaded.subgoal_space_from_env
    loaded.learn(45)
    # A model built with a box of its own is not held to its env's box either.
    box = SubgoalSpace(low=np.full(2, -2.0), high=np.full(2, 2.0), threshold=0.45)
    tiny_model(HIER, maze_env, subgoal_space=box).save(tmp_path / "own_box.zip")
    assert HIER.load(tmp_path / "own_box.zip", env=umaze()).subgoal_space.same_as(box)


# (saved, given to load): a learned coefficient for a fixed one, the other way round, and another fixed value, which
# the saved tensor would replace without a word.
REFUSED_ENTROPY_COEFFICIENTS = [("auto", 0.05), (0.05, "auto"), (0.05, 0.1)]


@pytest.mark.parametrize(
    ("model_class", "name"), [(HIER, "ent_coef"), (HIER, "high_ent_coef"), (DAC, "ent_coef"), (SACDemo, "ent_coef")]
)
@pytest.mark.parametrize(("saved", "given"), REFUSED_ENTROPY_COEFFICIENTS)
def test_an_entropy_coefficient_load_cannot_restore_is_refused(model_class, name, saved, given, tmp_path, maze_env):
    """The reported case: resuming with -params ent_coef:0.05 failed inside SB3 with "'NoneType' object has no attribute
    'load_state_dict'" (the saved model learned its coefficient)."""
    any_tiny_model(model_class, maze_env, **{name: saved}).save(tmp_path / "model.zip")
    message = rf"\({re.escape(str(tmp_path / 'model.zip'))}, ...\): the saved model .* \({name}={saved!r}\).*Leave {name} out"
    with pytest.raises(ValueError, match=message):
        model_class.load(tmp_path / "model.zip", env=maze_env, **{name: given})


@pytest.mark.parametrize(("saved", "given"), [("auto", "auto_0.5"), (0.05, "0.05")])
def test_an_entropy_coefficient_load_restores_as_given_is_accepted(saved, given, tmp_path, maze_env):
    tiny_model(HIER, maze_env, ent_coef=saved).save(tmp_path / "model.zip")
    loaded = HIER.load(tmp_path / "model.zip", env=maze_env, ent_coef=given)
    loaded.learn(45)
    assert (loaded.lower.ent_coef_optimizer is None) == (saved == 0.05)


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_loading_another_algorithms_file_names_the_class_that_saved_it(model_class, tmp_path, maze_env):
    any_tiny_model(model_class, maze_env).save(tmp_path / "model")
    other_class = ALL_ALGORITHMS[(ALL_ALGORITHMS.index(model_class) + 1) % len(ALL_ALGORITHMS)]
    name = model_class.__name__
    with pytest.raises(ValueError, match=rf"was saved by {name}; load it with {name}\.load, not {other_class.__name__}\.load"):
        other_class.load(tmp_path / "model")


# Algorithms that share a policy class are all named (sb3-contrib's TRPO is imported with TQC).
@pytest.mark.parametrize(
    ("library_class", "saver"),
    [
        (SAC, r"stable_baselines3\.SAC"),
        (TQC, r"sb3_contrib\.TQC"),
        (PPO, r"sb3_contrib\.TRPO or stable_baselines3\.A2C or stable_baselines3\.PPO"),
    ],
)
def test_loading_another_librarys_file_names_the_class_that_saved_it(library_class, saver, tmp_path, maze_env):
    library_class("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[8]), seed=0).save(tmp_path / "model")
    loader = rf"{saver}\.load" if " or " not in saver else "the one that saved it"
    for model_class in ALL_ALGORITHMS:
        message = rf"saved by {saver} \(its policy is .*\), not by an sb3-dipper algorithm: load it with {loader}, not "
        # Without an env SB3 alone failed on the missing subgoal space, with one on the missing lower optimizer.
        with pytest.raises(ValueError, match=message + rf"{model_class.__name__}\.load"):
            model_class.load(tmp_path / "model.zip")
        with pytest.raises(ValueError, match=message):
            model_class.load(tmp_path / "model.zip", env=maze_env)


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_a_file_of_ours_without_the_saving_class_still_loads(model_class, tmp_path, maze_env):
    # sb3-dipper 0.1.0 wrote no saved_by; its files hold the class's own settings (option_steps, ...).
    any_tiny_model(model_class, maze_env).save(tmp_path / "model")
    with zipfile.ZipFile(tmp_path / "model.zip") as saved, zipfile.ZipFile(tmp_path / "old.zip", "w") as old:
        for item in saved.namelist():
            content = saved.read(item)
            if item == "data":
                data = json.loads(content)
                del data["saved_by"]
                content = json.dumps(data).encode()
            old.writestr(item, content)
    loaded = model_class.load(tmp_path / "old.zip", env=maze_env)
    assert loaded.num_timesteps == 0 and not hasattr(loaded, "saved_by")


def test_a_policy_class_saved_by_value_is_not_guessed():
    serialized = base64.b64encode(pickle.dumps(Path)).decode()  # "pathlib.Path", but the data says another module
    assert _pickled_class_name({":serialized:": serialized, "__module__": "pathlib"}) == "pathlib.Path"
    assert _pickled_class_name({":serialized:": serialized, "__module__": "__main__"}) is None
    assert _pickled_class_name({":serialized:": "not base64!", "__module__": "pathlib"}) is None


# ---------------------------------------------------------------------------------------------------- logging, warnings


# DIPPER logs through its lower SAC, HIER through both inner SACs (flat algorithms log as SB3 does).
@pytest.mark.parametrize("model_class", [DIPPER, HIER])
def test_tensorboard_log_writes_an_event_file(model_class, tmp_path, maze_env):
    any_tiny_model(model_class, maze_env, tensorboard_log=str(tmp_path)).learn(60)
    assert list(tmp_path.rglob("events.out.tfevents.*"))


def render_mode_warnings(build) -> list[str]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        build()
    return [str(warning.message) for warning in caught if "render_mode" in str(warning.message)]


def test_the_lower_levels_env_has_no_render_mode_and_says_nothing(maze_env):
    model = tiny_model(DIPPER, maze_env)
    space = low_level_observation_space(maze_env.observation_space, model.subgoal_space)
    assert render_mode_warnings(lambda: SubgoalVecEnv(space, maze_env.action_space, model.subgoal_space, 2)) == []


def test_neither_levels_env_can_be_stepped_and_each_gives_its_rewards(maze_env):
    """The lower SAC's and HIER's higher SAC's envs are facades the option layer drives: they refuse a reset or a step,
    naming their level, and answer HER's compute_reward (the subgoal reward; the base env's)."""
    model = tiny_model(HIER, maze_env)
    lower_env, higher_env = model.lower.env, model.higher.env
    for env, level in ((lower_env, "lower"), (higher_env, "higher")):
        for call in (env.reset, lambda env=env: env.step(np.zeros((1, 2), np.float32))):
            with pytest.raises(RuntimeError, match=f"The {level} level's env is driven by the option layer"):
                call()
        assert env.env_is_wrapped(VecNormalize) == [False] and env.get_attr("num_envs") == [1]
    goals = np.zeros((3, 2), np.float32)
    far = goals + 10.0
    np.testing.assert_array_equal(lower_env.env_method("compute_reward", goals, far, {})[0], [-1.0] * 3)
    expected = maze_env.env_method("compute_reward", goals, far, [{}] * 3, indices=[0])[0]
    np.testing.assert_array_equal(higher_env.env_method("compute_reward", goals, far, [{}] * 3, indices=[0])[0], expected)
    with pytest.raises(AttributeError, match="only provides compute_reward"):
        lower_env.env_method("render")


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_building_a_model_emits_no_render_mode_warning(model_class, maze_env):
    assert render_mode_warnings(lambda: any_tiny_model(model_class, maze_env)) == []


# ---------------------------------------------------------------------------------------------------- export_policy


@pytest.mark.parametrize("model_class", OPTION_ALGORITHMS)
def test_the_exported_policy_acts_as_the_model(model_class, maze_env):
    model = any_tiny_model(model_class, maze_env)
    model.learn(60)
    exported = model.export_policy()
    assert isinstance(exported, HierarchicalPolicy)
    # model.policy is the higher level: its actions are subgoals in [-1, 1]^d, not primitive actions.
    high_action, _ = model.policy.predict(maze_env.reset(), deterministic=True)
    assert high_action.shape == (1, model.subgoal_space.dim)
    expected = rollout_actions(model, short_maze(seed=4))
    # The export is a copy: the model's later training leaves it as it was.
    with th.no_grad():
        for parameter in model.policy.parameters():
            parameter.add_(1.0)
    np.testing.assert_array_equal(rollout_actions(exported, short_maze(seed=4)), expected)


def test_the_exported_policy_keeps_the_normalisation_statistics():
    env = VecNormalize(short_maze(), norm_reward=False)
    model = tiny_model(DIPPER, env)
    model.learn(60)
    exported = model.export_policy()

    def evaluation_env() -> VecNormalize:
        normalized = VecNormalize(short_maze(seed=4), norm_reward=False, training=False)
        normalized.obs_rms = env.obs_rms
        return normalized

    np.testing.assert_array_equal(rollout_actions(exported, evaluation_env()), rollout_actions(model, evaluation_env()))


def test_a_planning_model_refuses_to_export(maze_env):
    with pytest.raises(NotImplementedError, match=r"model\.predict"):
        tiny_model(DIPPER, maze_env, planner_kwargs=dict(mode="subgoal")).export_policy()
