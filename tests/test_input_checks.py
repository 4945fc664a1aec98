"""Settings out of range, integer settings given as floats or strings, malformed goal spaces and non-finite terminal
observations are refused at construction and at load (or where the observation enters), with the parameter and its range named;
the dicts a constructor is given are left as they were."""

import copy
import inspect
import json
import math
import re
import warnings
import zipfile
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import SAC
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_dipper import DAC, DIPPER, HIER, PIPER, RAPS, SACDemo
from sb3_dipper.common.option_env import OptionVecEnv
from sb3_dipper.common.preferences import TrajectoryPairs
from sb3_dipper.common.subgoals import SubgoalSpace
from sb3_dipper.envs import PointMazeReachController
from tests.conftest import ALL_ALGORITHMS, HIERARCHICAL_ALGORITHMS, any_tiny_model, short_maze, tiny_model
from zoo_scripts.configs import make_model

NAN, INF = math.nan, math.inf
POSITIVE = "must be a finite number > 0"
NON_NEGATIVE = "must be a finite number >= 0"
DISCOUNT = r"must be a finite number in \(0, 1\]"
PROBABILITY = r"must be a finite number in \[0, 1\]"
ENTROPY_COEFFICIENT = r'must be .*"auto".*"auto_<initial value > 0>"'

# DAC and SACDemo are flat SB3 SACs, where gamma = 0 (a bandit) is meaningful: [0, 1] there.
FLAT_SACS = [DAC, SACDemo]
NOT_FLAT_SACS = [
    model for model in ALL_ALGORITHMS if model not in FLAT_SACS and "gamma" in inspect.signature(model).parameters
]

# (parameter, bad value, what the message says after the parameter's name, the classes if not all that have it)
BAD_SETTINGS = [
    ("beta", 0.0, POSITIVE, None),
    ("beta", -0.1, POSITIVE, None),
    ("beta", NAN, POSITIVE, None),
    ("pairs_per_batch", 0, "must be at least 1", None),
    ("batch_size", 0, "must be at least 1", None),
    ("high_batch_size", 0, "must be at least 1", None),
    ("reward_batch_size", 0, "must be at least 1", None),
    ("trajectory_buffer_size", 0, "must be at least", None),
    ("trajectory_buffer_size", 1, r"must be at least 2.*two stored trajectories", [DIPPER, PIPER]),
    ("value_steps", -1, "must be at least 0", None),
    ("train_freq", 0, "must be at least 1", None),
    ("option_steps", 2.5, r"must be a whole number \(an integer >= 1\)", None),
    ("max_episode_steps", 0, "must be at least 1", None),
    ("gamma", 0.0, DISCOUNT, NOT_FLAT_SACS),
    ("gamma", 1.5, DISCOUNT, NOT_FLAT_SACS),
    ("gamma", NAN, DISCOUNT, NOT_FLAT_SACS),
    ("gamma", -0.1, PROBABILITY, FLAT_SACS),
    ("gamma", 1.5, PROBABILITY, FLAT_SACS),
    ("gamma", NAN, PROBABILITY, FLAT_SACS),
    ("high_gamma", 1.5, DISCOUNT, None),
    ("tau", 0.0, DISCOUNT, None),
    ("high_tau", 2.0, DISCOUNT, None),
    ("buffer_size", 0, "must be at least 1", None),
    ("high_buffer_size", 0, "must be at least 1", None),
    ("nll_coef", -1.0, NON_NEGATIVE, None),
    ("gradient_penalty_coef", -10.0, NON_NEGATIVE, None),
    ("adversarial_coef", NAN, NON_NEGATIVE, None),
    ("value_reg_coef", -0.1, NON_NEGATIVE, None),
    ("n_preference_pairs", 0, "must be at least 1", None),
    ("learning_starts", -1, "must be at least 0", None),
    ("gradient_steps", -2, "must be at least", None),
    ("high_gradient_steps", -1, "must be at least 0", None),
    ("reward_gradient_steps", -1, "must be at least 0", None),
    ("segment_length", 0, "must be at least 1", None),
    ("segment_options", 0, "must be at least 1", None),
    ("segment_options", 2.5, r"must be a whole number \(an integer >= 1\)", None),
    ("greedy_episode_interval", 0, "must be at least 1", None),
    ("n_hindsight_goals", -1, "must be at least 0", None),
    ("target_update_interval", 0, "must be at least 1", None),
    ("stats_window_size", 0, "must be at least 1", None),
    ("random_subgoal_prob", NAN, PROBABILITY, None),
    ("n_steps", 0, "must be at least 1", None),
    ("learning_rate", -1e-3, NON_NEGATIVE, None),
    ("low_learning_rate", "abc", NON_NEGATIVE, None),
    ("reward_learning_rate", 0.0, POSITIVE, None),
    ("discriminator_learning_rate", INF, POSITIVE, None),
    ("ent_coef", -0.1, ENTROPY_COEFFICIENT, None),
    ("high_ent_coef", "auto_-1", ENTROPY_COEFFICIENT, None),
    ("high_ent_coef", "bogus", ENTROPY_COEFFICIENT, None),
    # On/off settings: the string "False" would be on.
    ("paper_compat", "False", "must be True or False, got 'False'", None),
    ("high_her", "False", "must be True or False, got 'False'", None),
    ("absorbing_states", "False", "must be True or False, got 'False'", None),
    ("goal_conditioned_discriminator", "no", "must be True or False, got 'no'", None),
    ("state_conditioned", "False", "must be True or False, got 'False'", None),
    ("demo_path", "", "must be an npz file, a Minari dataset directory", None),
]

# (demo_kwargs key, bad value, what the message says after demo_kwargs['key']), for every algorithm with demo_kwargs.
BAD_DEMO_SETTINGS = [
    ("n_demos", 0, "must be at least 1"),
    ("n_demos", 2.5, r"must be a whole number \(an integer >= 1\)"),
    ("demo_share", 1.5, PROBABILITY),
    ("bc_coef", -1.0, NON_NEGATIVE),
    ("bc_coef", NAN, NON_NEGATIVE),
    ("rl_coef", -1.0, NON_NEGATIVE),
    ("q_filter", "yes", "must be True or False, got 'yes'"),
    ("demo_path", "", "must be an npz file, a Minari dataset directory, 'auto' or 'auto:dart<N>'"),
    ("demo_path", 5, "must be an npz file, a Minari dataset directory, 'auto' or 'auto:dart<N>'"),
]

# (switch_kwargs key, bad value, what the message says after switch_kwargs['key']), for DIPPER.
BAD_SWITCH_SETTINGS = [
    ("nll_coef", -1.0, NON_NEGATIVE),
    ("label_smoothing", 0.5, r"must be a finite number in \[0, 0.5\)"),
    ("label_smoothing", -0.1, r"must be a finite number in \[0, 0.5\)"),
    ("value_score_coef", -1e-6, NON_NEGATIVE),
    ("value_score_coef", INF, NON_NEGATIVE),
    ("goal_subgoal_prob", 1.5, PROBABILITY),
    ("goal_episode_prob", -0.1, PROBABILITY),
    ("matched_control_prob", 1.5, PROBABILITY),
    ("matched_control_prob", 0.5, r"pairs a policy trajectory .* set switch_kwargs\['goal_episode_prob'\] above 0"),
    ("anchor_coef", -1.0, NON_NEGATIVE),
    ("hindsight_actions", "False", "must be True or False, got 'False'"),
    ("truncate_at_goal", 1, "must be True or False, got 1"),
    ("contrast_env_goals", "no", "must be True or False, got 'no'"),
    ("reference", "previous", r"'previous': choose one of \('uniform', 'averaged'\)"),
    ("value_reg", "papper", r"'papper': choose one of \('paper', 'score', 'reparam'\)"),
]

# Every integer-valued constructor setting; the zoo and YAML may hand any of them over as a float or a string.
INTEGER_SETTINGS = (
    "option_steps",
    "n_preference_pairs",
    "pairs_per_batch",
    "batch_size",
    "high_batch_size",
    "reward_batch_size",
    "buffer_size",
    "high_buffer_size",
    "trajectory_buffer_size",
    "value_steps",
    "learning_starts",
    "train_freq",
    "gradient_steps",
    "high_gradient_steps",
    "reward_gradient_steps",
    "max_episode_steps",
    "n_demos",
    "segment_length",
    "greedy_episode_interval",
    "n_hindsight_goals",
    "target_update_interval",
    "stats_window_size",
)


def constructor_parameters(model_class) -> dict[str, inspect.Parameter]:
    return dict(inspect.signature(model_class.__init__).parameters)


def bad_setting_cases():
    for name, value, message, classes in BAD_SETTINGS:
        having = [cls for cls in ALL_ALGORITHMS if name in constructor_parameters(cls)]
        assert having, f"no algorithm has a parameter {name!r}"
        for cls in classes or having:
            yield pytest.param(cls, name, value, message, id=f"{cls.__name__}-{name}={value}")


@pytest.fixture(scope="module")
def env():
    # Refused constructions never step the env, so one serves the whole module.
    venv = short_maze()
    yield venv
    venv.close()


@pytest.mark.parametrize(("model_class", "name", "value", "message"), list(bad_setting_cases()))
def test_a_setting_out_of_range_is_refused_at_construction(env, model_class, name, value, message):
    with pytest.raises(ValueError, match=f"{name} {message}"):
        any_tiny_model(model_class, env, **{name: value})


def stored_setting(model, name: str):
    """A setting as the model keeps it (SB3 keeps some under a private name, ``train_freq`` as a ``TrainFreq``)."""
    value = getattr(model, name) if hasattr(model, name) else getattr(model, f"_{name}")
    return value.frequency if name == "train_freq" and not isinstance(value, int) else value


@pytest.fixture(scope="module")
def saved_models(env, tmp_path_factory):
    """One saved tiny model of each algorithm, built from valid settings."""
    folder = tmp_path_factory.mktemp("saved")
    for model_class in ALL_ALGORITHMS:
        any_tiny_model(model_class, env).save(folder / f"{model_class.__name__}.zip")
    return folder


def with_saved_setting(saved: Path, path: Path, name: str, value) -> Path:
    """A copy of the model file ``saved`` at ``path`` whose data holds ``value`` for the setting ``name``."""
    with zipfile.ZipFile(saved) as archive:
        members = {member: archive.read(member) for member in archive.namelist()}
    data = json.loads(members["data"])
    key = name if name in data else f"_{name}"  # SB3 keeps some settings under a private name
    assert key in data, name
    data[key] = value
    members["data"] = json.dumps(data).encode()
    with zipfile.ZipFile(path, "w") as archive:
        for member, content in members.items():
            archive.writestr(member, content)
    return path


@pytest.mark.parametrize(("model_class", "name", "value", "message"), list(bad_setting_cases()))
def test_a_setting_out_of_range_in_a_saved_file_is_refused_at_load(saved_models, tmp_path, model_class, name, value, message):
    """load runs the constructor's checks on the settings it reads, and names the file."""
    path = with_saved_setting(saved_models / f"{model_class.__name__}.zip", tmp_path / "edited.zip", name, value)
    with pytest.raises(ValueError, match=f"{re.escape(str(path))} holds a setting .*: {name} {message}"):
        model_class.load(path)


def test_dipper_load_refuses_a_bad_beta_or_planning_mode_in_the_file_or_given_to_it(saved_models, tmp_path):
    """The reported cases: beta = -1 and planning = "bogus" in a zip's data went through load, predict and learn."""
    saved = saved_models / "DIPPER.zip"
    beta = with_saved_setting(saved, tmp_path / "beta.zip", "beta", -1.0)
    with pytest.raises(ValueError, match=rf"{re.escape(str(beta))} holds .*: beta must be a finite number > 0, got -1.0"):
        DIPPER.load(beta, env=short_maze())
    planning = with_saved_setting(saved, tmp_path / "planning.zip", "planner_kwargs", {"mode": "bogus"})
    with pytest.raises(ValueError, match=r"Unknown planning mode 'bogus': choose one of \('off', 'subgoal', 'waypoint'\)"):
        DIPPER.load(planning)
    planner = with_saved_setting(saved, tmp_path / "planner.zip", "planner_kwargs", {"mode": "subgoal", "lookahead": 0})
    with pytest.raises(
        ValueError, match=rf"{re.escape(str(planner))} holds .*lookahead must be at least 1, got 0.*planner_kwargs=\.\.\."
    ):
        DIPPER.load(planner)
    # planner_kwargs given to load replace their keys of the saved planner's settings, and keep the saved graph.
    loaded = DIPPER.load(saved, planner_kwargs={"lookahead": 3})
    assert loaded.planner.lookahead == 3 and loaded.planner.mode == DIPPER.load(saved).planner.mode
    # A value given to load is checked too, and said to come from there.
    with pytest.raises(ValueError, match=rf"DIPPER.load\({re.escape(str(saved))}, beta=-1.0\): beta must be"):
        DIPPER.load(saved, beta=-1.0)
    # Settings given to load as the zoo's YAML gives them are converted as the constructor converts them.
    assert DIPPER.load(saved, pairs_per_batch="8.0").pairs_per_batch == 8


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_integer_settings_given_as_whole_floats_become_ints(env, model_class):
    names = [name for name in INTEGER_SETTINGS if name in constructor_parameters(model_class)]
    # n_demos defaults to None (all the episodes demo_path makes): given, it is converted as the others are.
    reference = any_tiny_model(model_class, env, **({"n_demos": 1} if "n_demos" in names else {}))
    given = {name: float(stored_setting(reference, name)) for name in names}
    model = any_tiny_model(model_class, env, **given)
    for name in names:
        assert type(stored_setting(model, name)) is int and stored_setting(model, name) == given[name], name


@pytest.mark.parametrize("model_class", [*HIERARCHICAL_ALGORITHMS, RAPS])
def test_integer_settings_given_as_strings_become_ints(env, model_class):
    model = any_tiny_model(model_class, env, option_steps="5", learning_starts="40")
    assert (model.option_steps, model.learning_starts) == (5, 40)


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_learning_rates_and_entropy_coefficients_given_as_strings_become_numbers(env, model_class):
    # YAML reads 1e-3 without !!float as a string.
    model = any_tiny_model(model_class, env, learning_rate="1e-3")
    assert model.learning_rate == 1e-3
    if "ent_coef" in constructor_parameters(model_class):
        assert any_tiny_model(model_class, env, ent_coef="0.05").ent_coef == 0.05


@pytest.mark.parametrize("value", [2.5, "abc", True, None])
@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_a_non_integer_for_an_integer_setting_is_refused_at_once(env, model_class, value):
    with pytest.raises(ValueError, match=r"learning_starts must be a whole number \(an integer >= 0\), got"):
        any_tiny_model(model_class, env, learning_starts=value)


def test_float_settings_from_the_zoo_train_past_learning_starts():
    """The reported case: ``-params n_preference_pairs:5e4 option_steps:20.0`` crashed in numpy once training began."""
    env = short_maze()
    model = tiny_model(DIPPER, env, option_steps=5.0, n_preference_pairs=2e2, pairs_per_batch=8.0, trajectory_buffer_size=5e1)
    model.learn(80)
    assert model.num_timesteps == 80 and len(model.preferences) > 0


# Every dict a constructor takes, with a content the algorithms that take it accept.
DICT_SETTINGS = {
    "policy_kwargs": {"net_arch": [16]},
    "low_policy_kwargs": {"net_arch": [16]},
    "replay_buffer_kwargs": {"n_sampled_goal": 2},
    "high_replay_buffer_kwargs": {"n_sampled_goal": 2},
    "low_level_kwargs": {"target_update_interval": 1},
    "reward_model_kwargs": {"net_arch": [16]},
    "discriminator_kwargs": {"net_arch": [16]},
    "demo_kwargs": {"demo_path": "auto", "bc_coef": 0.01},
    "switch_kwargs": {"nll_coef": 1.0},
}


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_the_dicts_given_to_a_constructor_are_left_as_they_were(model_class):
    names = [name for name in DICT_SETTINGS if name in constructor_parameters(model_class)]
    given = {name: copy.deepcopy(DICT_SETTINGS[name]) for name in names}
    assert "policy_kwargs" in given
    model = any_tiny_model(model_class, short_maze(), **given)
    model.learn(45)
    assert given == {name: DICT_SETTINGS[name] for name in given}
    # What the model keeps (and saves) is what it was given, not what its inner SACs added to their copies (DAC is an
    # SB3 SAC itself, which keeps use_sde among its own policy_kwargs).
    if not isinstance(model, SAC):
        assert model.policy_kwargs == DICT_SETTINGS["policy_kwargs"]


# ---------------------------------------------------------------------------------------------------- demo_kwargs


@pytest.mark.parametrize("model_class", HIERARCHICAL_ALGORITHMS)
def test_normalize_from_demos_given_as_a_string_is_refused(env, model_class):
    with pytest.raises(ValueError, match=r"demo_kwargs\['normalize_from_demos'\] must be True or False, got 'False'"):
        any_tiny_model(model_class, env, demo_kwargs=dict(demo_path="auto", normalize_from_demos="False"))


def test_the_planners_in_predict_given_as_a_string_is_refused(env):
    with pytest.raises(ValueError, match=r"in_predict must be True or False, got 'False'"):
        any_tiny_model(DIPPER, env, planner_kwargs=dict(mode="subgoal", in_predict="False"))


@pytest.mark.parametrize("model_class", [*HIERARCHICAL_ALGORITHMS, SACDemo])
@pytest.mark.parametrize(("key", "value", "message"), BAD_DEMO_SETTINGS)
def test_a_demo_setting_out_of_range_is_refused_naming_its_demo_kwargs_key(env, model_class, key, value, message):
    with pytest.raises(ValueError, match=rf"demo_kwargs\['{key}'\] {message}"):
        any_tiny_model(model_class, env, demo_kwargs={key: value})


def test_a_demo_setting_is_checked_given_by_its_deprecated_name_in_a_file_and_to_load(saved_models, tmp_path):
    with pytest.warns(DeprecationWarning), pytest.raises(ValueError, match=rf"demo_kwargs\['bc_coef'\] {NON_NEGATIVE}"):
        tiny_model(HIER, short_maze(), bc_coef=-1.0)
    saved = saved_models / "HIER.zip"
    edited = with_saved_setting(saved, tmp_path / "edited.zip", "demo_kwargs", {"demo_share": 2.0})
    with pytest.raises(
        ValueError,
        match=rf"{re.escape(str(edited))} holds .*: demo_kwargs\['demo_share'\] {PROBABILITY}.*HIER.load\(path, demo_kwargs=",
    ):
        HIER.load(edited)
    with pytest.raises(ValueError, match=r"HIER.load\(.*, demo_kwargs=\{.*'rl_coef': -1.0.*\}\): demo_kwargs\['rl_coef'\]"):
        HIER.load(saved, demo_kwargs={"rl_coef": -1.0})


@pytest.mark.parametrize("model_class", [*HIERARCHICAL_ALGORITHMS, SACDemo])
def test_a_demo_setting_without_demonstrations_is_refused_naming_the_missing_demo_path(env, model_class):
    with pytest.raises(
        ValueError,
        match=r"demo_kwargs\['bc_coef'\]=0.02, demo_kwargs\['q_filter'\]=False without demonstrations changes nothing: "
        r"give demo_kwargs\['demo_path'\] too .*, or leave bc_coef, q_filter out",
    ):
        any_tiny_model(model_class, env, demo_kwargs=dict(bc_coef=0.02, q_filter=False))
    # The defaults, given or not, are no demonstration setting of the user's.
    assert any_tiny_model(model_class, env, demo_kwargs=dict(bc_coef=0.0078)).demo_kwargs["demo_path"] is None


def test_demo_settings_from_the_zoo_are_converted_and_a_misspelt_key_is_named(env):
    model = tiny_model(HIER, env, demo_kwargs={"demo_path": "auto", "n_demos": "1.0", "bc_coef": "1e-2"})
    assert model.demo_kwargs["n_demos"] == 1 and type(model.demo_kwargs["n_demos"]) is int
    assert model.demo_kwargs["bc_coef"] == 0.01 and model.lower.bc_coef == 0.01
    with pytest.raises(TypeError, match=r"^demo_kwargs got an unexpected key 'bc_coeff'; did you mean 'bc_coef'\?$"):
        tiny_model(HIER, env, demo_kwargs={"bc_coeff": 1.0})
    # A misspelt deprecated name is answered with its new form.
    misspelt = r"HIER got an unexpected keyword argument 'bc_coeff'; did you mean demo_kwargs\['bc_coef'\]\?$"
    with pytest.raises(TypeError, match=misspelt):
        tiny_model(HIER, env, bc_coeff=1.0)


# ---------------------------------------------------------------------------------------------------- switch_kwargs


@pytest.mark.parametrize(("key", "value", "message"), BAD_SWITCH_SETTINGS)
def test_a_switch_out_of_range_is_refused_naming_its_switch_kwargs_key(env, key, value, message):
    with pytest.raises(ValueError, match=rf"switch_kwargs\['{key}'\] {message}"):
        tiny_model(DIPPER, env, switch_kwargs={key: value})


def test_a_switch_is_checked_in_a_file_given_to_load_and_set_on_a_built_model(saved_models, tmp_path, env):
    saved = saved_models / "DIPPER.zip"
    edited = with_saved_setting(saved, tmp_path / "edited.zip", "switch_kwargs", {"goal_subgoal_prob": 2.0})
    with pytest.raises(
        ValueError,
        match=rf"{re.escape(str(edited))} holds .*: switch_kwargs\['goal_subgoal_prob'\] {PROBABILITY}"
        r".*DIPPER.load\(path, switch_kwargs=",
    ):
        DIPPER.load(edited)
    with pytest.raises(
        ValueError, match=r"DIPPER.load\(.*, switch_kwargs=\{'nll_coef': -1.0.*\}\): switch_kwargs\['nll_coef'\]"
    ):
        DIPPER.load(saved, switch_kwargs={"nll_coef": -1.0})
    # switch_kwargs given to load replace their keys of the saved ones.
    loaded = DIPPER.load(saved, switch_kwargs={"hindsight_actions": True})
    assert loaded.switch_kwargs == {**DIPPER.load(saved).switch_kwargs, "hindsight_actions": True}
    # A switch set on a built model is checked, and acts, when it next learns.
    model = tiny_model(DIPPER, env)
    model.switch_kwargs["label_smoothing"] = 0.5
    with pytest.raises(ValueError, match=r"switch_kwargs\['label_smoothing'\] must be"):
        model.learn(10)
    assert model.preference_pipeline.sampler.contrast_env_goals
    model.switch_kwargs.update(label_smoothing=0.0, truncate_at_goal=True, contrast_env_goals=False)
    model.learn(10)
    sampler = model.preference_pipeline.sampler
    assert sampler.goal_reached is not None and not sampler.contrast_env_goals


def test_switches_from_the_zoo_are_converted_and_a_misspelt_key_is_named(env):
    model = tiny_model(DIPPER, env, switch_kwargs={"nll_coef": "1e-2", "goal_subgoal_prob": 1})
    assert model.switch_kwargs["nll_coef"] == 0.01 and type(model.switch_kwargs["goal_subgoal_prob"]) is float
    with pytest.raises(TypeError, match=r"^switch_kwargs got an unexpected key 'nll_coeff'; did you mean 'nll_coef'\?$"):
        tiny_model(DIPPER, env, switch_kwargs={"nll_coeff": 1.0})
    with pytest.raises(TypeError, match=r"^switch_kwargs got an unexpected key 'planning'; its keys are nll_coef, "):
        tiny_model(DIPPER, env, switch_kwargs={"planning": "subgoal"})
    misspelt = (
        r"DIPPER got an unexpected keyword argument 'hindsight_action'; did you mean switch_kwargs\['hindsight_actions'\]\?$"
    )
    with pytest.raises(TypeError, match=misspelt):
        tiny_model(DIPPER, env, hindsight_action=True)


def test_one_policy_kwargs_dict_builds_hier_then_dipper(env):
    """The reported case: HIER's higher SAC wrote use_sde into the dict, which DIPPER's policy then refused."""
    policy_kwargs = {"net_arch": [16]}
    tiny_model(HIER, env, policy_kwargs=policy_kwargs)
    dipper = tiny_model(DIPPER, env, policy_kwargs=policy_kwargs)
    assert policy_kwargs == {"net_arch": [16]} and dipper.policy_kwargs == policy_kwargs


# ---------------------------------------------------------------------------------------------------- goal spaces


class GoalEnv(gym.Env):
    """A goal env whose goal spaces and threshold a test chooses."""

    action_space = spaces.Box(-1, 1, (2,))

    def __init__(self, achieved_goal: spaces.Box, desired_goal: spaces.Box, distance_threshold: float | None = None):
        self.observation_space = spaces.Dict(
            {"observation": spaces.Box(-1, 1, (4,)), "achieved_goal": achieved_goal, "desired_goal": desired_goal}
        )
        if distance_threshold is not None:
            self.distance_threshold = distance_threshold


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_achieved_and_desired_goals_of_different_shapes_are_refused(model_class):
    env = GoalEnv(spaces.Box(-1, 1, (2,)), spaces.Box(-1, 1, (3,)), distance_threshold=0.1)
    with pytest.raises(ValueError, match=r"same shape, but achieved_goal is \(2,\) and desired_goal is \(3,\)"):
        model_class("MultiInputPolicy", env)


@pytest.mark.parametrize("model_class", [*HIERARCHICAL_ALGORITHMS, RAPS])
def test_a_bounded_goal_space_without_distance_threshold_says_the_threshold_is_missing(model_class):
    env = GoalEnv(spaces.Box(-1, 1, (2,)), spaces.Box(-1, 1, (2,)))
    with pytest.raises(ValueError, match="No subgoal space is known") as error:
        model_class("MultiInputPolicy", env)
    message = str(error.value)
    assert "no `distance_threshold` attribute" in message and "unbounded" not in message
    assert "subgoal_space=SubgoalSpace(low, high, threshold)" in message and "register_subgoal_space" in message


@pytest.mark.parametrize("model_class", [*HIERARCHICAL_ALGORITHMS, RAPS])
def test_an_unbounded_goal_space_with_distance_threshold_says_it_is_unbounded(model_class):
    env = GoalEnv(spaces.Box(-np.inf, np.inf, (2,)), spaces.Box(-np.inf, np.inf, (2,)), distance_threshold=0.05)
    with pytest.raises(ValueError, match="No subgoal space is known") as error:
        model_class("MultiInputPolicy", env)
    message = str(error.value)
    assert "achieved_goal space is unbounded" in message and "distance_threshold" not in message
    assert "subgoal_space=SubgoalSpace(low, high, threshold)" in message and "register_subgoal_space" in message


@pytest.mark.parametrize("model_class", HIERARCHICAL_ALGORITHMS)
@pytest.mark.parametrize(
    ("name", "value", "message"),
    [
        ("replay_buffer_kwargs", dict(n_sampled_goal=-2), r"replay_buffer_kwargs\['n_sampled_goal'\] must be at least 0"),
        (
            "replay_buffer_kwargs",
            dict(goal_selection_strategy="futur"),
            r"replay_buffer_kwargs\['goal_selection_strategy'\] 'futur': choose one of",
        ),
        ("replay_buffer_kwargs", dict(n_sampled_goals=4), r"replay_buffer_kwargs got an unexpected key 'n_sampled_goals'"),
        (
            "low_level_kwargs",
            dict(buffer_size=5),
            r"low_level_kwargs\['buffer_size'\] is set by the hierarchy: use buffer_size",
        ),
        ("low_level_kwargs", dict(learning_rate=1e-4), r"low_level_kwargs\['learning_rate'\] .* use low_learning_rate"),
        ("low_level_kwargs", dict(target_update_intervall=2), r"'target_update_intervall' \(from low_level_kwargs\); did you"),
    ],
)
def test_the_lower_sacs_dicts_are_checked_naming_the_parameter(env, model_class, name, value, message):
    """A negative n_sampled_goal would relabel every sampled transition; the others would fail inside SB3, naming it."""
    with pytest.raises((ValueError, TypeError), match=message):
        any_tiny_model(model_class, env, **{name: value})


@pytest.mark.parametrize(
    "model_class", [model for model in ALL_ALGORITHMS if "high_replay_buffer_kwargs" in constructor_parameters(model)]
)
def test_the_higher_her_buffers_kwargs_are_checked(env, model_class):
    with pytest.raises(ValueError, match=r"high_replay_buffer_kwargs\['n_sampled_goal'\] must be at least 0"):
        any_tiny_model(model_class, env, high_replay_buffer_kwargs=dict(n_sampled_goal=-1))


@pytest.mark.parametrize("model_class", HIERARCHICAL_ALGORITHMS)
@pytest.mark.parametrize(
    ("subgoal_space", "message"),
    [
        (SubgoalSpace([-1, -1, -1], [1, 1, 1], 0.5), r"has 3 dimensions, but its subgoals control 2 entries"),
        (SubgoalSpace([-1, -1], [1, 1], 0.5, indices=(0, 5)), r"indices \(0, 5\) reach beyond the env's achieved_goal"),
        (spaces.Box(-1, 1, (2,)), "subgoal_space must be a sb3_dipper.common.subgoals.SubgoalSpace"),
    ],
)
def test_a_subgoal_space_that_does_not_fit_the_env_is_refused_at_construction(env, model_class, subgoal_space, message):
    with pytest.raises(ValueError, match=message):
        any_tiny_model(model_class, env, subgoal_space=subgoal_space)


# ---------------------------------------------------------------------------------------------------- observations


class NaNAtEpisodeEnd(gym.Wrapper):
    """The last observation of each episode (SB3's ``info["terminal_observation"]``) holds a NaN."""

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        if terminated or truncated:
            obs = dict(obs, observation=np.full_like(obs["observation"], np.nan))
        return obs, reward, terminated, truncated, info


def test_a_nan_terminal_observation_is_refused_with_its_key_and_env_index():
    def make(nan_at_end: bool):
        def thunk():
            env = gym.make("PointMazeFourRooms-v0", max_episode_steps=8)
            return NaNAtEpisodeEnd(env) if nan_at_end else env

        return thunk

    venv = DummyVecEnv([make(False), make(True)])
    venv.seed(0)
    option_env = OptionVecEnv(venv, venv.get_attr("subgoal_space", indices=[0])[0], 10, PointMazeReachController())
    option_env.reset()
    # The episodes end at the 8th step of the option; env 1's next observation (after its reset) is finite.
    with pytest.raises(ValueError, match=r"info\['terminal_observation'\]\) key 'observation' holds NaN.*env indices \[1\]"):
        option_env.step(np.zeros((2, 2), np.float32))


# ---------------------------------------------------------------------------------------------------- DIPPER's value score


def random_pairs(model, n_pairs: int = 4) -> TrajectoryPairs:
    rng = np.random.default_rng(0)
    steps = model.high_steps
    observations = {
        key: rng.uniform(-1, 1, size=(2, n_pairs, steps, *space.shape)).astype(np.float32)
        for key, space in model.observation_space.spaces.items()
    }
    actions = rng.uniform(-1, 1, size=(2, n_pairs, steps, model.subgoal_space.dim)).astype(np.float32)
    return TrajectoryPairs(
        observations=observations,
        actions=actions,
        reached_actions=actions,
        next_achieved_goals=observations["achieved_goal"],
        mask=np.ones((2, n_pairs, steps), dtype=bool),
        labels=np.full(n_pairs, 0.5),
    )


def test_the_score_value_term_has_its_own_coefficient_at_pipers_scale(env):
    model = tiny_model(DIPPER, env, switch_kwargs=dict(value_reg="score"), value_reg_coef=0.1)
    assert model.switch_kwargs["value_score_coef"] == 1e-6
    assert model.preference_pipeline.labeler.value_score == model._pair_value_score
    pairs = random_pairs(model)
    th.manual_seed(0)  # the lower value is taken at a sampled lower action
    score = model._pair_value_score(pairs)
    model.switch_kwargs["value_score_coef"] = 1.0
    th.manual_seed(0)
    summed_values = model._pair_value_score(pairs)
    assert np.abs(summed_values).max() > 0.0
    # value_reg_coef (0.1, the paper's lambda) plays no part: the sum of lower values is weighed by 1e-6.
    np.testing.assert_allclose(score, 1e-6 * summed_values, rtol=1e-5)


def test_dac_keeps_sb3s_minus_one_gradient_steps(env):
    """SB3's ``gradient_steps=-1`` (as many as steps collected) stays allowed where SB3 runs the loop."""
    assert any_tiny_model(DAC, env, gradient_steps=-1).gradient_steps == -1


def test_hier_refuses_no_updates_for_the_lower_level(env):
    """The option loop has no "-1": a negative count would silently skip every lower update."""
    with pytest.raises(ValueError, match="gradient_steps must be at least 0, got -1"):
        any_tiny_model(HIER, env, gradient_steps=-1)


# ---------------------------------------------------------------------------------------------------- misspelt keywords


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_a_misspelt_keyword_names_the_class_and_the_parameter_it_resembles(env, model_class):
    with pytest.raises(
        TypeError,
        match=rf"^{model_class.__name__} got an unexpected keyword argument 'learning_start'; "
        r"did you mean 'learning_starts'\?$",
    ):
        any_tiny_model(model_class, env, learning_start=40)
    with pytest.raises(TypeError, match=rf"'colour'; see help\({model_class.__name__}\) for its parameters$"):
        any_tiny_model(model_class, env, colour="blue")


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_a_misspelt_keyword_given_to_load_is_refused_not_set_aside(saved_models, model_class):
    """SB3's load sets every keyword as an attribute: a misspelt one would leave the setting meant at its saved value."""
    path = saved_models / f"{model_class.__name__}.zip"
    with pytest.raises(
        TypeError,
        match=rf"^{model_class.__name__} got an unexpected keyword argument 'learning_start' "
        rf"\(from {model_class.__name__}.load\(.*\)\); did you mean 'learning_starts'\?$",
    ):
        model_class.load(path, learning_start=10)
    # A parameter, and an attribute saved with the model, are set as SB3 sets them.
    loaded = model_class.load(path, learning_starts=10, _n_updates=3)
    assert (loaded.learning_starts, loaded._n_updates) == (10, 3)


@pytest.mark.parametrize("model_class", ALL_ALGORITHMS)
def test_the_constructor_keeps_its_explicit_signature(model_class):
    # SB3's contract: the parameters are the constructor's own (help(), the docs, rl-zoo3 and Optuna read them).
    parameters = inspect.signature(model_class).parameters
    assert list(parameters) == list(constructor_parameters(model_class))[1:]
    assert "learning_starts" in parameters and all(p.kind is not p.VAR_KEYWORD for p in parameters.values())


def test_a_misspelt_key_of_a_yaml_entry_names_the_file_for_sb3s_classes_too():
    with pytest.raises(
        TypeError,
        match=r"^SAC got an unexpected keyword argument 'gradient_step' \(from .*sac\.yml or "
        r"the overrides\); did you mean 'gradient_steps'\?$",
    ):
        make_model("sac", "PointMazeFourRooms-v0", seed=0, overrides={"gradient_step": 2})


# ---------------------------------------------------------------------------------------------------- option length


@pytest.mark.parametrize("model_class", [*HIERARCHICAL_ALGORITHMS, RAPS])
def test_options_longer_than_the_episode_are_warned_about(env, model_class):
    # The maze's episodes have 20 steps.
    with pytest.warns(UserWarning, match=r"option_steps=25 is longer than the episode \(max_episode_steps=20\)"):
        any_tiny_model(model_class, env, option_steps=25)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        any_tiny_model(model_class, env, option_steps=20)
    assert not [warning for warning in caught if "option_steps" in str(warning.message)]
