"""The two sets of hyperparameters: CPU profiles in hyperparams/<algo>.yml, paper scale in hyperparams/paper/<algo>.yml."""

import inspect
from pathlib import Path

import numpy as np
import pytest
import torch as th
import yaml
from stable_baselines3.common.vec_env import VecNormalize

from sb3_dipper.common.hierarchical import HierarchicalAlgorithm
from sb3_dipper.common.imitation import DEFAULT_DEMO_KWARGS
from sb3_dipper.dipper import DEFAULT_SWITCH_KWARGS
from sb3_dipper.zoo import ZOO_ALGORITHMS, hyperparams_dir
from tests.tools.test_zoo import PAPER_TASKS
from zoo_scripts.configs import load_entry, make_model

PAPER_DIR = hyperparams_dir() / "paper"
ALGOS = sorted(path.stem for path in hyperparams_dir().glob("*.yml"))
# Widest network and largest batch a CPU profile may use: one core trains it within about 90 minutes per run.
CPU_WIDTH, CPU_BATCH = 256, 256


def widest_layer(entry: dict) -> int:
    return max(
        (width for key in ("policy_kwargs", "low_policy_kwargs") for width in entry.get(key, {}).get("net_arch", [0])),
        default=0,
    )


def test_every_algorithm_has_a_paper_scale_file_with_every_paper_task():
    assert sorted(path.stem for path in PAPER_DIR.glob("*.yml")) == ALGOS
    for algo in ALGOS:
        entries = yaml.safe_load((PAPER_DIR / f"{algo}.yml").read_text())
        assert set(PAPER_TASKS) | {"default"} <= set(entries), algo


@pytest.mark.parametrize("algo", ALGOS)
def test_cpu_profiles_are_cpu_sized_and_paper_files_are_paper_sized(algo):
    for env_id in [*PAPER_TASKS, "default"]:
        cpu = load_entry(algo, env_id)
        paper = load_entry(algo, env_id, PAPER_DIR)
        assert widest_layer(cpu) <= CPU_WIDTH and cpu.get("batch_size", 0) <= CPU_BATCH, (algo, env_id)
        assert widest_layer(paper) == 512, (algo, env_id)
        # K, the demonstration and the budget-independent settings of the algorithm stay the paper's, but for the
        # demonstrations a run measured beyond the paper's one.
        for key in ("option_steps", "segment_length", "beta", "value_reg_coef", "ent_coef", "gamma"):
            assert cpu.get(key) == paper.get(key), (algo, env_id, key)
        expected = MEASURED_DEMONSTRATIONS.get((algo, env_id))
        assert demo_path(cpu) == (expected or demo_path(paper)), (algo, env_id)


def demo_path(entry: dict) -> str | None:
    """The demonstrations of an entry: in ``demo_kwargs`` for the hierarchical algorithms, DAC's own parameter."""
    return entry.get("demo_kwargs", {}).get("demo_path", entry.get("demo_path"))


FETCH_MANIPULATION = ("FetchPickAndPlace-v4", "FetchPickAndPlaceFixed-v0", "FetchPush-v4", "FetchPushFixed-v0")
LONG_EPISODE_TASKS = ("FetchFourRoomMaze-v0", "FetchFourRoomMazeFixed-v0", "FrankaKitchenMicrowaveBurner-v0")


# RAPS decides once per scripted primitive of several steps, and its file keeps SB3's rate for those decisions.
@pytest.mark.parametrize("algo", [algo for algo in ALGOS if algo != "raps"])
def test_maze_and_kitchen_profiles_train_at_the_authors_rate_of_ten_batches_per_episode(algo):
    for env_id in LONG_EPISODE_TASKS:
        entry = load_entry(algo, env_id)
        assert (entry.get("train_freq"), entry.get("gradient_steps")) == (45, 4), (algo, env_id)


@pytest.mark.parametrize("algo", ALGOS)
def test_fetch_manipulation_entries_run_the_papers_grid_of_seven_options_of_seven_steps(algo):
    for directory in (hyperparams_dir(), PAPER_DIR):
        for env_id in FETCH_MANIPULATION:
            entry = load_entry(algo, env_id, directory)
            assert entry.get("env_kwargs") == {"max_episode_steps": 49}, (algo, env_id, directory)
            assert entry.get("option_steps", 7) == 7, (algo, env_id, directory)


def test_a_fetch_manipulation_model_makes_seven_decisions_per_episode():
    model, env, _ = make_model("dipper_paper", "FetchPushFixed-v0", seed=0, overrides=dict(buffer_size=1000))
    assert env.get_attr("spec")[0].max_episode_steps == 49
    assert (model.option_steps, model.high_steps) == (7, 7)
    env.close()


# Where a run showed that more demonstrations help (research log docs/research/2026-11-30-paper-tasks-cpu.md, entries
# 2026-12-03 "The kitchen's lower level is a noisy clone", 2026-12-04 "Twenty DART episodes on the random pick-and-place
# and push" and 2026-12-04 "The random push learnt from 200 DART episodes"), the CPU profile names them; the paper-scale
# file keeps the paper's one demonstration.
KITCHEN = "FrankaKitchenMicrowaveBurner-v0"
DART_EPISODES = {KITCHEN: "auto:dart20", "FetchPickAndPlace-v4": "auto:dart20", "FetchPush-v4": "auto:dart200"}
# Every method that takes demonstrations learns from DIPPER's there, so that no row's advantage is its demonstrations'.
CLONING_ALGOS = ["dipper", "dipper_paper", "dipper_nov", "hier", "hac", "piper", "saga", "sac_demo"]
MEASURED_DEMONSTRATIONS = {(algo, env_id): path for algo in [*CLONING_ALGOS, "dac"] for env_id, path in DART_EPISODES.items()}


def dart_profile(env_id: str, episodes: int, monkeypatch, cache: Path):
    """The task's ``dipper`` profile as a zoo user gets it, its DART episodes made in process into ``cache``, checked
    to clone all ``episodes`` of them unfiltered at weight 1.0 from 128 demonstration steps per lower batch (the
    authors' 128 of 1024). Returns what ``make_model`` returns."""
    monkeypatch.setenv("SB3_DIPPER_CACHE", str(cache))
    model, env, n_timesteps = make_model("dipper", env_id, seed=0, overrides=dict(buffer_size=1000))
    demonstrations = model.lower.demonstrations
    assert demonstrations is not None and model.lower.demo_share * model.batch_size == 128
    assert len(np.unique(demonstrations.last_step)) == episodes
    assert not model.lower.q_filter and model.lower.bc_coef == 1.0
    return model, env, n_timesteps


def test_the_kitchen_profile_clones_twenty_dart_episodes_at_the_authors_demonstration_batch(tmp_path, monkeypatch):
    """The measured kitchen configuration, with observations scaled by the demonstrations."""
    _, env, n_timesteps = dart_profile(KITCHEN, 20, monkeypatch, tmp_path)
    assert n_timesteps == 675_000
    assert isinstance(env, VecNormalize) and not env.training, "statistics fixed to the demonstrations' states"
    env.close()


def test_the_random_push_profile_clones_two_hundred_dart_episodes(tmp_path, monkeypatch):
    """The measured random push configuration: the random pick-and-place's, whose goal-anchored policy acts alone at
    evaluation (the planner steers training only)."""
    model, env, n_timesteps = dart_profile("FetchPush-v4", 200, monkeypatch, tmp_path)
    assert n_timesteps == 640_000
    assert model.switch_kwargs["goal_episode_prob"] == 0.5 and not model.switch_kwargs["hindsight_actions"]
    assert model.planner.mode == "subgoal" and not model.planner.in_predict
    assert model.policy.goal_anchored and model.preference_source == "progress"
    env.close()


@pytest.mark.parametrize("algo", ["dipper", "dipper_paper", "dipper_nov", "hier", "piper", "sac", "dac", "sac_demo"])
def test_paper_scale_entries_build(algo):
    model, env, n_timesteps = make_model(
        algo, "FetchPickAndPlaceFixed-v0", seed=0, hyperparams=PAPER_DIR, overrides=dict(buffer_size=1000)
    )
    assert n_timesteps == 9e5
    assert model.batch_size == 1024
    if isinstance(model, HierarchicalAlgorithm):
        assert model.lower.bc_coef == AUTHORS_BC_COEF["FetchPickAndPlaceFixed-v0"]
    if algo == "sac_demo":
        assert model.bc_coef == AUTHORS_BC_COEF["FetchPickAndPlaceFixed-v0"] and model.demonstrations is not None
    env.close()


# The authors' code weighs its lower level's behaviour cloning per task (lambda_2 in ddpg.py), for 128 demonstration
# steps of a 1024 batch, which the paper-scale files keep (demo_share 0.125).
AUTHORS_BC_COEF = {
    "FetchPickAndPlace-v4": 0.005,
    "FetchPickAndPlaceFixed-v0": 0.005,
    "FetchPush-v4": 0.0078,
    "FetchPushFixed-v0": 0.0078,
    "FrankaKitchenMicrowaveBurner-v0": 0.001,
}


@pytest.mark.parametrize("algo", ["dipper", "dipper_paper", "dipper_nov", "hier", "hac", "piper", "saga", "sac_demo"])
def test_paper_scale_files_weigh_behaviour_cloning_as_the_authors(algo):
    for env_id, bc_coef in AUTHORS_BC_COEF.items():
        settings = cloning_settings(algo, env_id, PAPER_DIR)
        assert settings["demo_path"] == "auto", (algo, env_id)
        assert settings["bc_coef"] == bc_coef, (algo, env_id)


def test_an_entry_in_the_form_before_demo_kwargs_and_switch_kwargs_builds_the_same_model_with_a_warning(tmp_path):
    """The YAML files of before (the lower level's demonstration settings and DIPPER's switches as keys of their own),
    and the zoo's ``-params bc_coef:...`` or ``nll_coef:...`` on top of an entry in the new form, still work."""
    new_form = "  demo_kwargs: {demo_path: 'auto', bc_coef: 0.02}\n"
    new_switches = (
        "  switch_kwargs: {nll_coef: 1.0, hindsight_actions: False, truncate_at_goal: True, goal_episode_prob: 0.5}\n"
    )
    text = (hyperparams_dir() / "dipper.yml").read_text()
    assert new_form in text and new_switches in text
    text = text.replace(new_form, "  demo_path: 'auto'\n  bc_coef: 0.02\n")
    (tmp_path / "dipper.yml").write_text(
        # goal_episode_prob came with switch_kwargs: the old names join the dict's other keys.
        text.replace(
            new_switches,
            "  nll_coef: 1.0\n  hindsight_actions: False\n  truncate_at_goal: True\n"
            "  switch_kwargs: {goal_episode_prob: 0.5}\n",
        )
    )
    overrides = dict(buffer_size=1000)
    old_form = r"demo_path, bc_coef are deprecated: pass demo_kwargs=\{'demo_path': 'auto', 'bc_coef': 0.02\}"
    old_switches = r"nll_coef, hindsight_actions, truncate_at_goal are deprecated: pass switch_kwargs=\{'nll_coef': 1.0, "
    with pytest.warns(DeprecationWarning, match=old_form), pytest.warns(DeprecationWarning, match=old_switches):
        old, old_env, _ = make_model("dipper", "FetchPickAndPlaceFixed-v0", seed=0, overrides=overrides, hyperparams=tmp_path)
    new, new_env, _ = make_model("dipper", "FetchPickAndPlaceFixed-v0", seed=0, overrides=overrides)
    assert old.demo_kwargs == new.demo_kwargs and new.demo_kwargs["bc_coef"] == old.lower.bc_coef == 0.02
    assert old.switch_kwargs == new.switch_kwargs and new.switch_kwargs["truncate_at_goal"]
    with pytest.warns(DeprecationWarning, match=r"bc_coef is deprecated: pass demo_kwargs=\{'bc_coef': 0.5\} instead"):
        overridden, env, _ = make_model("dipper", "FetchPickAndPlaceFixed-v0", seed=0, overrides={**overrides, "bc_coef": 0.5})
    assert overridden.demo_kwargs == {**new.demo_kwargs, "bc_coef": 0.5}
    with pytest.warns(DeprecationWarning, match=r"nll_coef is deprecated: pass switch_kwargs=\{'nll_coef': 0.0\} instead"):
        no_nll, no_nll_env, _ = make_model(
            "dipper", "FetchPickAndPlaceFixed-v0", seed=0, overrides={**overrides, "nll_coef": 0.0}
        )
    assert no_nll.switch_kwargs == {**new.switch_kwargs, "nll_coef": 0.0}
    no_nll_env.close()
    for venv in (old_env, new_env, env):
        venv.close()


CLONING_SETTINGS = ("demo_path", "n_demos", "demo_share", "bc_coef", "rl_coef", "q_filter")


def cloning_settings(algo: str, env_id: str, directory: Path) -> dict:
    """The demonstration and cloning settings an entry builds its model with (its ``demo_kwargs``), the defaults
    included."""
    assert "demo_kwargs" in inspect.signature(ZOO_ALGORITHMS[algo]).parameters, algo
    demo_kwargs = {**DEFAULT_DEMO_KWARGS, **load_entry(algo, env_id, directory).get("demo_kwargs", {})}
    return {key: demo_kwargs[key] for key in CLONING_SETTINGS}


def test_sac_demo_entries_are_sac_with_dippers_demonstrations_and_cloning():
    """The flat row with cloning differs from SAC+HER only by the cloning, and clones what DIPPER clones."""
    for directory in (hyperparams_dir(), PAPER_DIR):
        for env_id in ["PointMazeFourRooms-v0", *PAPER_TASKS, "default"]:
            entry = load_entry("sac_demo", env_id, directory)
            without_cloning = {key: value for key, value in entry.items() if key != "demo_kwargs"}
            assert without_cloning == load_entry("sac", env_id, directory), (directory, env_id)
            assert cloning_settings("sac_demo", env_id, directory) == cloning_settings("dipper", env_id, directory), (
                directory,
                env_id,
            )


@pytest.mark.parametrize("env_id", DART_EPISODES)
@pytest.mark.parametrize("algo", CLONING_ALGOS)
def test_every_method_clones_dippers_demonstrations_as_dipper_where_its_profile_takes_dart_episodes(algo, env_id):
    assert cloning_settings(algo, env_id, hyperparams_dir()) == cloning_settings("dipper", env_id, hyperparams_dir())
    if algo != "sac_demo":  # SACDemo has no scaling by the demonstrations' states (hyperparams/sac_demo.yml)
        normalized = load_entry(algo, env_id)["demo_kwargs"].get("normalize_from_demos", False)
        assert normalized == load_entry("dipper", env_id)["demo_kwargs"].get("normalize_from_demos", False)


@pytest.mark.parametrize("env_id", DART_EPISODES)
def test_dac_discriminates_against_dippers_demonstrations_where_its_profile_takes_dart_episodes(env_id):
    entry, dipper = load_entry("dac", env_id), cloning_settings("dipper", env_id, hyperparams_dir())
    assert (entry["demo_path"], entry["n_demos"]) == (dipper["demo_path"], dipper["n_demos"])


# Tasks where a run showed the switches beyond the paper help (BENCHMARKS.md, "the paper's tasks on a CPU"), and which.
MEASURED_SWITCHES = {
    "FetchPickAndPlaceFixed-v0": {"nll_coef", "truncate_at_goal", "goal_episode_prob"},
    "FetchPushFixed-v0": {"nll_coef", "truncate_at_goal", "goal_episode_prob"},
    "FetchPickAndPlace-v4": {"nll_coef", "truncate_at_goal", "goal_episode_prob"},
    "FetchPush-v4": {"nll_coef", "truncate_at_goal", "goal_episode_prob"},
    "FetchFourRoomMazeFixed-v0": {"nll_coef", "truncate_at_goal", "goal_episode_prob"},
    "FetchFourRoomMaze-v0": {"nll_coef", "truncate_at_goal", "goal_episode_prob"},
}


def test_dipper_switches_are_on_only_where_measured():
    """No switch beyond the paper is on for a paper task until a measurement there shows it helps."""
    for directory in (hyperparams_dir(), PAPER_DIR):
        for env_id in PAPER_TASKS:
            entry = load_entry("dipper", env_id, directory)
            measured = directory == hyperparams_dir() and env_id in MEASURED_SWITCHES
            switches_on = {key for key, value in entry.get("switch_kwargs", {}).items() if value != DEFAULT_SWITCH_KWARGS[key]}
            assert switches_on == (MEASURED_SWITCHES[env_id] if measured else set()), (directory, env_id)
            assert ("planner_kwargs" in entry) == measured, (directory, env_id)
            assert ("acting_tau" in entry["policy_kwargs"]) == measured, (directory, env_id)
            assert load_entry("dipper_paper", env_id, directory)["policy_kwargs"].get("acting_tau") is None


@pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.parametrize("algo", ["dipper", "sac"])
def test_paper_scale_trains_on_cuda(algo):
    model, env, _ = make_model(
        algo, "FetchPickAndPlaceFixed-v0", seed=0, hyperparams=PAPER_DIR, overrides=dict(learning_starts=100), device="cuda"
    )
    model.learn(300)
    assert next(model.policy.parameters()).is_cuda
    env.close()
