"""Preferences from people: the label queue, the asynchronous source, NoisyLabeler, the page, and training on late labels."""

import csv
import http.client
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium.wrappers import TimeLimit
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import configure

from sb3_dipper import DIPPER, PIPER, DPOFlat
from sb3_dipper.common.files import save_npz
from sb3_dipper.common.preferences import (
    PreferenceDataset,
    PreferenceSource,
    PrimitiveInTheLoopLabeler,
    TrajectoryPairs,
    add_new_labels,
    pairs_due,
)
from sb3_dipper.envs import PointMazeFourRoomsEnv
from sb3_dipper.labelling.app import MAX_BODY_BYTES, LabellingServer, create_app, serve_in_background
from sb3_dipper.labelling.drawable import DRAWN_ENVS
from sb3_dipper.labelling.queue import ANSWERS, PERSON, SCRIPT, LabelQueue
from sb3_dipper.labelling.render import PairRenderer
from sb3_dipper.labelling.sources import (
    PAIRS_A_PERSON_LABELS_A_MINUTE,
    PEOPLE_PAIRS_WARNING_THRESHOLD,
    NoisyLabeler,
    QueuedPreferenceSource,
    label_queue_directory,
    preference_source_from,
)
from sb3_dipper.zoo import RunControl, split_run_control
from tests.conftest import any_tiny_model, short_maze

REPO = Path(__file__).resolve().parent.parent


def goal_reached(achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
    return np.linalg.norm(achieved - desired, axis=-1) <= 0.5


SCRIPT_LABELER = PrimitiveInTheLoopLabeler(goal_reached)


def random_pairs(n_pairs: int, seed: int = 0, length: int = 3) -> TrajectoryPairs:
    """Pairs whose trajectories wander around a goal at the origin: some reach it, some not."""
    rng = np.random.default_rng(seed)
    shape = (2, n_pairs, length, 2)
    observations = {
        "observation": rng.normal(size=shape).astype(np.float32),
        "achieved_goal": rng.normal(size=shape).astype(np.float32),
        "desired_goal": np.zeros(shape, np.float32),
    }
    return TrajectoryPairs(
        observations=observations,
        actions=rng.uniform(-1, 1, size=shape).astype(np.float32),
        reached_actions=rng.uniform(-1, 1, size=shape).astype(np.float32),
        next_achieved_goals=rng.normal(size=shape).astype(np.float32),
        mask=np.ones((2, n_pairs, length), bool),
        labels=np.full(n_pairs, np.nan, np.float32),
    )


def people(directory, env=None, **kwargs) -> QueuedPreferenceSource:
    """A people source on ``directory``; with ``env`` (a VecEnv), the queue records it for the page to draw."""
    return preference_source_from(QueuedPreferenceSource(str(directory), **kwargs), SCRIPT_LABELER, env)


# ---------------------------------------------------------------------------------------------------- the source


def test_queued_pairs_wait_and_arrive_labelled(tmp_path):
    source = people(tmp_path)
    pairs = random_pairs(5)
    started = time.monotonic()
    labels = source.label(pairs)
    assert time.monotonic() - started < 1.0  # queuing, not waiting for a person
    assert np.isnan(labels).all() and source.pending == 5 and source.collect() is None

    dataset = PreferenceDataset(10)
    add_new_labels(dataset, source, TrajectoryPairs(**{**pairs.__dict__, "labels": labels}))
    assert len(dataset) == 0  # waiting pairs are not trained on

    queue = LabelQueue(tmp_path)
    assert queue.waiting_ids() == [0, 1, 2, 3, 4]
    for pair_id, label in [(3, 1.0), (0, 0.0), (1, float("nan"))]:
        assert queue.record_answer(pair_id, label)
    add_new_labels(dataset, source, None)
    stored = dataset.all_pairs()
    assert len(dataset) == 2 and stored.labels.tolist() == [0.0, 1.0]  # skipped pair 1 is dropped
    np.testing.assert_array_equal(stored.next_achieved_goals, pairs.next_achieved_goals[:, [0, 3]])
    np.testing.assert_array_equal(stored.observations["observation"], pairs.observations["observation"][:, [0, 3]])
    assert source.pending == 2 and source.collect() is None  # each label is handed over once
    record = queue.read_handed()
    assert record["pair_id"].tolist() == [0, 3] and (record["labeller"] == PERSON).all()


def test_pending_pairs_count_against_the_label_budget(tmp_path):
    dataset = PreferenceDataset(10)
    assert pairs_due(dataset, 10, 100, 100) == 10
    assert pairs_due(dataset, 10, 100, 100, pending=7) == 3
    assert pairs_due(dataset, 10, 100, 100, pending=10) == 0

    # The source's own budget: the most pairs ever queued for people in its directory, across sources.
    source = QueuedPreferenceSource(str(tmp_path), budget=3)  # no script: pairs beyond the budget get no label
    assert np.isnan(source.label(random_pairs(2))).all()
    labels = people(tmp_path, budget=3).label(random_pairs(4, seed=1))
    assert LabelQueue(tmp_path).queued_ids() == [0, 1, 2]  # one more fitted the budget
    assert np.isnan(labels[0]) and np.array_equal(labels[1:], SCRIPT_LABELER.label(random_pairs(4, seed=1))[1:])


def test_a_hand_over_record_without_its_arrays_is_named_with_the_fix(tmp_path):
    queue = LabelQueue(tmp_path)
    np.savez(queue.handed_path, pair_id=np.arange(2))  # edited by hand: no label, no labeller
    with pytest.raises(ValueError, match=r"Malformed hand-over record .*: missing \['label', 'labeller'\]\. Delete it"):
        queue.read_handed()


def test_reuse_labels_given_as_a_string_is_refused(tmp_path):
    # "False" would be on: a restarted run would take the labels in the directory that it was told to leave.
    with pytest.raises(ValueError, match="reuse_labels must be True or False, got 'False'"):
        QueuedPreferenceSource(str(tmp_path), reuse_labels="False")


def people_warnings(caught: list[warnings.WarningMessage]) -> list[str]:
    return [str(warning.message) for warning in caught if "asks people for" in str(warning.message)]


@pytest.mark.parametrize("model_class", [DIPPER, PIPER, DPOFlat])
def test_a_label_budget_beyond_what_people_label_is_warned_about_once_at_setup(tmp_path, model_class):
    """The maze profile's budget, 50,000 pairs, sent to people: the queue would grow by 256 files a training round."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = any_tiny_model(model_class, short_maze(), preference_source=f"people:{tmp_path}", n_preference_pairs=50_000)
        # DPO-FLAT sets its source up when it first learns; before learning_starts, so no pair is queued yet.
        model.learn(10)
        model.learn(10, reset_num_timesteps=False)
    [message] = people_warnings(caught)
    assert "n_preference_pairs=50,000 asks people for up to 50,000 pairs" in message and str(tmp_path) in message
    assert "hours of labelling" in message and f"'budget': {60 * PAIRS_A_PERSON_LABELS_A_MINUTE}" in message


@pytest.mark.parametrize(
    "spec, label_budget, asked",
    [("people:{dir}", PEOPLE_PAIRS_WARNING_THRESHOLD, None), ("people:{dir}", 4000, 4000),
     ("mixed:{dir}:0.25", 4000, None), ("mixed:{dir}:0.3", 4000, 1200),
     (dict(kind="people", directory="{dir}", budget=300), 50_000, None),
     (dict(kind="people", directory="{dir}", budget=2000), 50_000, 2000)],
)  # fmt: skip
def test_the_warning_counts_only_the_pairs_people_are_asked_for(tmp_path, spec, label_budget, asked):
    if isinstance(spec, str):
        spec = spec.replace("{dir}", str(tmp_path))
    else:
        spec = {**spec, "directory": str(tmp_path)}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        preference_source_from(spec, SCRIPT_LABELER, label_budget=label_budget)
    messages = people_warnings(caught)
    if asked is None:
        assert messages == []
    else:
        assert len(messages) == 1 and f"asks people for up to {asked:,} pairs" in messages[0]


def test_mixed_mode_records_who_labelled_each_pair(tmp_path):
    pairs = random_pairs(40)
    source = people(tmp_path, person_fraction=0.25, seed=3)
    labels = source.label(pairs)
    queued = np.isnan(labels)
    assert 3 <= queued.sum() <= 20 and source.pending == queued.sum()
    np.testing.assert_array_equal(labels[~queued], SCRIPT_LABELER.label(pairs)[~queued])

    queue = LabelQueue(tmp_path)
    for pair_id in queue.waiting_ids():
        queue.record_answer(pair_id, 0.5)
    assert len(source.collect()) == queued.sum()
    record = queue.read_handed()
    labeller = dict(zip(record["pair_id"].tolist(), record["labeller"].tolist(), strict=True))
    assert sorted(labeller) == list(range(40))
    assert [labeller[pair_id] for pair_id in range(40)] == [PERSON if q else SCRIPT for q in queued]

    # A predicate instead of a share: pairs whose first trajectory starts left of the goal go to people.
    left = lambda batch: batch.observations["achieved_goal"][0, :, 0, 0] < 0  # noqa: E731
    chosen = people(tmp_path / "predicate", to_person=left).label(pairs)
    np.testing.assert_array_equal(np.isnan(chosen), left(pairs))


def test_label_file_from_a_killed_writer_is_old_or_new(tmp_path):
    """A writer killed at any moment leaves labels.npz whole: the answers it had recorded, maybe one fewer."""
    queue = LabelQueue(tmp_path)
    for kill in range(4):
        child = os.fork()
        if child == 0:  # the writer: records answers until it is killed
            try:
                writer = LabelQueue(tmp_path)
                for pair_id in range(100000):
                    writer.record_answer(pair_id, float(pair_id % 2))
            finally:
                os._exit(0)
        time.sleep(0.15 + 0.05 * kill)
        os.kill(child, signal.SIGKILL)
        os.waitpid(child, 0)
        answers = queue.answers()  # reads whole, or raises
        ids = answers.pair_ids.tolist()
        assert ids == list(range(len(ids))) and len(ids) > 0
        np.testing.assert_array_equal(answers.labels, np.arange(len(ids)) % 2)
        queue.labels_path.unlink()


def test_a_restarted_source_and_page_resume(tmp_path, maze_env):
    first = people(tmp_path, maze_env)
    first.label(random_pairs(4))
    queue = LabelQueue(tmp_path)
    queue.record_answer(1, 1.0)
    queue.record_answer(2, float("nan"))

    # A new training process adopts the waiting pairs, gets the label given meanwhile, and uses fresh ids.
    second = people(tmp_path, maze_env)
    assert second.pending == 2
    assert second.collect().labels.tolist() == [1.0]
    second.label(random_pairs(1))
    assert queue.queued_ids() == [0, 1, 2, 3, 4]

    # A restarted page goes on with the unanswered pairs; a skipped pair comes back only when asked.
    assert LabellingServer(tmp_path).next_pair("tab")["pair_id"] == 0
    assert LabellingServer(tmp_path).waiting() == [0, 3, 4]
    again = LabellingServer(tmp_path, show_skipped=True)
    assert again.waiting() == [0, 2, 3, 4]
    again.next_pair("tab")
    for side in ("left", "right"):  # the page shows the pair first
        again.image(2, side)
    assert again.answer(2, "tab", "left")[1] == 200
    assert queue.answers().as_dict()[2] == 1.0


def test_two_tabs_never_label_one_pair_twice(tmp_path, maze_env):
    people(tmp_path, maze_env).label(random_pairs(3))
    client = create_app(tmp_path).test_client()
    first = client.post("/api/next", json={"client": "a"}).get_json()["pair_id"]
    second = client.post("/api/next", json={"client": "b"}).get_json()["pair_id"]
    assert first == 0 and second == 1  # each tab gets its own pair
    assert client.post("/api/next", json={"client": "a"}).get_json()["pair_id"] == 0  # a reload keeps the tab's pair
    for side in ("left", "right"):  # tab a shows its pair
        assert client.get(f"/api/pair/0/{side}.png").status_code == 200
    assert client.post("/api/label", json={"pair_id": 0, "client": "b", "answer": "right"}).status_code == 409
    assert client.post("/api/label", json={"pair_id": 0, "client": "a", "answer": "left"}).status_code == 200
    assert client.post("/api/label", json={"pair_id": 0, "client": "a", "answer": "right"}).status_code == 409
    assert client.post("/api/label", json={"pair_id": 0, "client": "a", "answer": "maybe"}).status_code == 400

    # Answers racing for one pair from threads (several page processes even): exactly one is recorded.
    queue = LabelQueue(tmp_path)
    results: list[bool] = []
    threads = [threading.Thread(target=lambda: results.append(LabelQueue(tmp_path).record_answer(2, 0.0))) for _ in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sorted(results) == [False] * 7 + [True]
    assert queue.answers().pair_ids.tolist() == [0, 2]


# ---------------------------------------------------------------------------------------------------- NoisyLabeler


def test_noisy_labeler_flips_at_its_rate_and_breaks_ties_at_random():
    pairs = random_pairs(20000, seed=5, length=2)
    scripted = SCRIPT_LABELER.label(pairs)
    strict, ties = scripted != 0.5, scripted == 0.5
    assert strict.sum() > 2000 and ties.sum() > 2000
    labels = NoisyLabeler(0.2, seed=0, script=SCRIPT_LABELER).label(pairs)
    assert set(np.unique(labels).tolist()) == {0.0, 1.0}
    flips = np.mean(labels[strict] != scripted[strict])
    assert abs(flips - 0.2) < 0.015, flips
    assert abs(np.mean(labels[ties]) - 0.5) < 0.03
    np.testing.assert_array_equal(labels, NoisyLabeler(0.2, seed=0, script=SCRIPT_LABELER).label(pairs))
    np.testing.assert_array_equal(NoisyLabeler(0.0, script=SCRIPT_LABELER).label(pairs)[strict], scripted[strict])
    with pytest.raises(ValueError, match=r"noise must be a probability in \[0, 0.5\]"):
        NoisyLabeler(0.7)


@pytest.mark.parametrize(
    "spec, kind",
    [(None, PrimitiveInTheLoopLabeler), ("primitive", PrimitiveInTheLoopLabeler), ("noisy:0.1", NoisyLabeler),
     ("noisy:0.1:4", NoisyLabeler), (dict(kind="noisy", noise=0.3), NoisyLabeler), ("people:{dir}", QueuedPreferenceSource),
     ("mixed:{dir}:0.3", QueuedPreferenceSource), (dict(kind="people", directory="{dir}", budget=5), QueuedPreferenceSource)],
)  # fmt: skip
def test_preference_source_specs(tmp_path, spec, kind):
    if isinstance(spec, str):
        spec = spec.replace("{dir}", str(tmp_path))
    elif isinstance(spec, dict):
        spec = {key: value.replace("{dir}", str(tmp_path)) if isinstance(value, str) else value for key, value in spec.items()}
    source = preference_source_from(spec, SCRIPT_LABELER, seed=1)
    assert type(source) is kind
    if kind is not PrimitiveInTheLoopLabeler:
        assert source.script is SCRIPT_LABELER


@pytest.mark.parametrize("spec", ["noisy", "noisy:lots", "people", "crowd:x", dict(kind="noisy", level=1), 3])
def test_bad_preference_source_names_the_parameter(spec):
    with pytest.raises(ValueError, match="preference_source"):
        preference_source_from(spec, SCRIPT_LABELER)


# ---------------------------------------------------------------------------------------------------- training


@pytest.mark.parametrize("model_class", [DIPPER, PIPER, DPOFlat])
def test_algorithms_train_on_labels_that_arrive_late(tmp_path, model_class):
    env = short_maze()
    model = any_tiny_model(model_class, env, preference_source=f"people:{tmp_path}", n_preference_pairs=4)
    model.learn(120)
    assert len(model.preferences) == 0 and model.preference_pipeline.labeler.pending == 4 and model._n_updates == 0
    assert isinstance(model.preference_source, str)  # the configured source; the live one is not saved
    queue = LabelQueue(tmp_path)
    given = {pair_id: label for pair_id, label in zip(queue.waiting_ids(), [1.0, 0.0, 0.5, np.nan], strict=True)}
    for pair_id, label in given.items():
        queue.record_answer(pair_id, label)

    model.learn(60, reset_num_timesteps=False)
    labelled = [pair_id for pair_id, label in given.items() if not np.isnan(label)]
    assert model.preferences.all_pairs().labels.tolist() == [given[pair_id] for pair_id in labelled]
    np.testing.assert_array_equal(
        model.preferences.all_pairs().next_achieved_goals,
        np.concatenate([queue.read_pair(pair_id).next_achieved_goals for pair_id in labelled], axis=1),
    )
    assert model._n_updates > 0
    model.save(tmp_path / "model.zip")
    env.close()


def model_with_waiting_pairs(tmp_path, model_class):
    """A tiny model whose people's label queue holds four waiting pairs, none labelled yet."""
    env = short_maze()
    model = any_tiny_model(model_class, env, preference_source=f"people:{tmp_path / 'labels'}", n_preference_pairs=4)
    model.learn(120)
    return env, model, LabelQueue(tmp_path / "labels")


@pytest.mark.parametrize("model_class", [DIPPER, PIPER, DPOFlat])
def test_a_restored_model_gets_only_the_labels_given_since_its_save(tmp_path, model_class):
    """A checkpoint's dataset holds the pairs handed before it was saved: resuming hands only the labels given since."""
    env, model, queue = model_with_waiting_pairs(tmp_path, model_class)
    first, second, third, _ = queue.waiting_ids()
    queue.record_answer(first, 1.0)
    queue.record_answer(second, 0.0)
    model.learn(60, reset_num_timesteps=False)
    assert model.preferences.all_pairs().labels.tolist() == [1.0, 0.0]
    model.save(tmp_path / "model.zip")
    model.save_replay_buffer(tmp_path / "buffer.pkl")

    queue.record_answer(third, 0.5)  # given while training was down
    resumed = model_class.load(tmp_path / "model.zip", env=env)
    resumed.load_replay_buffer(tmp_path / "buffer.pkl")
    resumed.learn(60, reset_num_timesteps=False)
    assert resumed.preferences.all_pairs().labels.tolist() == [1.0, 0.0, 0.5]
    assert queue.read_handed()["pair_id"].tolist() == [first, second, third]
    # A model started afresh on the same queue reuses every label given (reuse_labels=True).
    fresh = any_tiny_model(model_class, env, preference_source=f"people:{tmp_path / 'labels'}", n_preference_pairs=4)
    fresh.learn(60)
    assert sorted(fresh.preferences.all_pairs().labels.tolist()) == [0.0, 0.5, 1.0]
    env.close()


@pytest.mark.parametrize("model_class", [DIPPER, PIPER, DPOFlat])
def test_labels_handed_over_after_a_checkpoint_come_back_when_it_is_resumed(tmp_path, model_class):
    """Training took a label after its last save, then was killed: the checkpoint's dataset lacks it, so it comes back."""
    env, model, queue = model_with_waiting_pairs(tmp_path, model_class)
    first, second, third, _ = queue.waiting_ids()
    queue.record_answer(first, 1.0)
    model.learn(60, reset_num_timesteps=False)
    model.save(tmp_path / "model.zip")
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    queue.record_answer(second, 0.0)
    queue.record_answer(third, 0.5)
    model.learn(60, reset_num_timesteps=False)  # takes both, then the run is killed before its next save
    assert model.preferences.all_pairs().labels.tolist() == [1.0, 0.0, 0.5]
    assert queue.read_handed()["pair_id"].tolist() == [first, second, third]

    resumed = model_class.load(tmp_path / "model.zip", env=env)
    resumed.load_replay_buffer(tmp_path / "buffer.pkl")
    resumed.learn(60, reset_num_timesteps=False)
    assert resumed.preferences.all_pairs().labels.tolist() == [1.0, 0.0, 0.5]
    assert resumed.preferences.handed_ids.tolist() == [first, second, third]
    env.close()


def test_hand_edited_labels_and_queued_pairs_are_checked_as_preference_files_are(tmp_path):
    source = people(tmp_path)
    source.label(random_pairs(2))
    queue = LabelQueue(tmp_path)
    queue.record_answer(0, 1.0)
    arrays = dict(np.load(queue.labels_path))
    save_npz(queue.labels_path, {**arrays, "label": np.array([2.0], np.float32)})
    with pytest.raises(ValueError, match=r"labels.npz: label must hold 0, 0.5, 1 or NaN \(skipped\), got \[2.0\]"):
        source.collect()

    save_npz(queue.labels_path, arrays)
    pair = dict(np.load(queue.pair_path(0)))
    pair["observations/observation"][0, 0, 1, 0] = np.nan
    save_npz(queue.pair_path(0), pair)
    with pytest.raises(ValueError, match=r"queued pair .*00000000.npz: observations/observation holds NaN"):
        source.collect()


def test_noise_is_chosen_from_the_constructor(maze_env):
    model = any_tiny_model(DIPPER, maze_env, preference_source="noisy:0.25")
    assert isinstance(model.preference_pipeline.labeler, NoisyLabeler) and model.preference_pipeline.labeler.noise == 0.25
    assert isinstance(model.preference_pipeline.labeler.script, PrimitiveInTheLoopLabeler)


class ConstantLabeler(PreferenceSource):
    """Every pair gets the same label."""

    def __init__(self, label: float):
        self.constant = label

    def label(self, pairs: TrajectoryPairs) -> np.ndarray:
        return np.full(pairs.labels.shape, self.constant, dtype=np.float32)


TIE_SHARE_KEY = {DIPPER: "train/high_tie_share", PIPER: "train/high_tie_share", DPOFlat: "train/tie_share"}


@pytest.mark.parametrize("model_class", [DIPPER, PIPER, DPOFlat])
@pytest.mark.parametrize(("label", "tie_share"), [(0.5, 1.0), (1.0, 0.0)])
def test_the_share_of_ties_the_preference_learner_trains_on_is_logged(model_class, label, tie_share, tmp_path):
    """A tie carries no preference, so a share near 1 says the labels leave nothing to learn (the kitchen's case)."""
    model = any_tiny_model(model_class, short_maze(), preference_source=ConstantLabeler(label))
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(200, log_interval=1)
    with open(tmp_path / "progress.csv") as log:
        logged = [row[TIE_SHARE_KEY[model_class]] for row in csv.DictReader(log)]
    shares = [float(value) for value in logged if value != ""]
    assert shares and all(share == tie_share for share in shares)


# ---------------------------------------------------------------------------------------------------- the page


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.fixture
def chromium():
    webdriver = pytest.importorskip("selenium.webdriver")
    binary, driver = shutil.which("chromium"), shutil.which("chromedriver")
    if binary is None or driver is None:
        pytest.fail("The browser test needs chromium and chromium-driver: `make test` installs them (apt-get)")
    options = webdriver.ChromeOptions()
    options.binary_location = binary
    for argument in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=1100,800"):
        options.add_argument(argument)
    browser = webdriver.Chrome(options=options, service=webdriver.ChromeService(executable_path=driver))
    yield browser
    browser.quit()


@pytest.fixture
def page(tmp_path):
    """A tiny DIPPER run's queue of four pairs, and the labelling page serving it (the console script's code)."""
    model = any_tiny_model(DIPPER, short_maze(), preference_source=f"people:{tmp_path / 'labels'}", n_preference_pairs=4)
    model.learn(120)
    assert model.preference_pipeline.labeler.pending == 4
    port = free_port()
    server = subprocess.Popen(
        [sys.executable, "-m", "sb3_dipper.labelling.app", "--run", str(tmp_path), "--port", str(port)],
        env={**os.environ, "MUJOCO_GL": "egl"},
        stderr=subprocess.DEVNULL,
    )
    try:
        wait_until_serving(server, port)
    except AssertionError:
        server.kill()
        raise
    yield f"http://127.0.0.1:{port}/", model, tmp_path / "labels"
    server.terminate()
    server.wait(timeout=10)


def test_labelling_page_in_a_browser_trains_dipper(chromium, page):
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    url, model, directory = page
    chromium.get(url)
    wait = WebDriverWait(chromium, 60)  # each pair's frames are rendered on demand, slowly on a loaded machine

    def shown_pair() -> int:
        wait.until(lambda browser: browser.find_element(By.ID, "pair-id").text not in ("", "-"))
        loaded = "return arguments[0].complete && arguments[0].naturalWidth"
        for side in ("left", "right"):
            image = chromium.find_element(By.ID, f"{side}-img")
            wait.until(lambda _, image=image: chromium.execute_script(loaded, image))
        # The buttons are enabled once both pictures have loaded.
        wait.until(lambda browser: browser.find_element(By.ID, "btn-left").is_enabled())
        return int(chromium.find_element(By.ID, "pair-id").text)

    answers = {}
    first = shown_pair()
    chromium.find_element(By.ID, "btn-left").click()
    answers[first] = 1.0
    second = wait.until(lambda _: shown_pair() != first and shown_pair())
    chromium.find_element(By.TAG_NAME, "body").send_keys("d")  # the keyboard: right is better
    answers[second] = 0.0
    third = wait.until(lambda _: shown_pair() not in answers and shown_pair())
    chromium.find_element(By.ID, "btn-equal").click()
    answers[third] = 0.5
    fourth = wait.until(lambda _: shown_pair() not in answers and shown_pair())
    chromium.find_element(By.ID, "btn-skip").click()
    wait.until(lambda browser: browser.find_element(By.ID, "pair-id").text == "-")
    assert chromium.find_element(By.ID, "labelled").text == "3" and chromium.find_element(By.ID, "waiting").text == "0"

    recorded = LabelQueue(directory).answers().as_dict()
    assert sorted(recorded) == sorted([first, second, third, fourth]) and np.isnan(recorded[fourth])
    assert {pair_id: recorded[pair_id] for pair_id in answers} == answers
    assert json.loads((directory / "queue.json").read_text())["env_id"] == "PointMazeFourRooms-v0"

    # The model, trained on after the labels arrived, holds exactly those pairs and ran DPO updates on them.
    actor = [parameter.detach().clone() for parameter in model.policy.actor.parameters()]
    assert model._n_updates == 0
    model.learn(60, reset_num_timesteps=False)
    labelled = sorted(answers)
    assert model.preferences.all_pairs().labels.tolist() == [answers[pair_id] for pair_id in labelled]
    np.testing.assert_array_equal(
        model.preferences.all_pairs().observations["achieved_goal"],
        np.concatenate([LabelQueue(directory).read_pair(i).observations["achieved_goal"] for i in labelled], axis=1),
    )
    assert model._n_updates > 0
    assert any(not th.equal(before, after) for before, after in zip(actor, model.policy.actor.parameters(), strict=True))


def test_fetch_pairs_are_drawn_as_frame_strips():
    """Fetch: the object put back where each option left it, rendered headless, one strip per trajectory."""
    env = gym.make("FetchPickAndPlace-v4")
    obs, _ = env.reset(seed=0)
    length = 3
    pairs = random_pairs(1, length=length)
    pairs.observations = {key: np.broadcast_to(value, (2, 1, length, value.size)).copy() for key, value in obs.items()}
    pairs.next_achieved_goals = pairs.observations["achieved_goal"] + np.array([0.0, 0.05, 0.0])
    renderer = PairRenderer({"env_id": "FetchPickAndPlace-v4", "env_kwargs": {}, "subgoal_space": None})
    pictures = [renderer.render(pairs, side) for side in ("left", "right")]
    renderer.close()
    env.close()
    for png in pictures:
        assert png.startswith(b"\x89PNG") and len(png) > 10_000


class EnvWithoutRenderMode(gym.Env):
    """An env whose constructor takes no ``render_mode``: the page cannot make it to draw its pairs."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (2,))
    action_space = gym.spaces.Box(-1.0, 1.0, (2,))


def env_without_render_mode():
    env_id = "LabellingTestWithoutRenderMode-v0"
    if env_id not in gym.registry:
        gym.register(env_id, entry_point=EnvWithoutRenderMode)
    return make_vec_env(env_id)


@pytest.mark.parametrize(
    ("make_env", "reason"),
    [
        (lambda: make_vec_env(PointMazeFourRoomsEnv), "the pairs of this env (it has no registered id"),
        (env_without_render_mode, "gymnasium.make('LabellingTestWithoutRenderMode-v0', render_mode='rgb_array') failed"),
        (lambda: make_vec_env("CartPole-v1"), "env 'CartPole-v1' (CartPoleEnv is not a kind of env the page draws)"),
        (lambda: make_vec_env("FetchFourRoomMaze-v0"), "(FetchFourRoomMazeEnv's maze is not a gymnasium-robotics maze map"),
    ],
    ids=["unregistered", "no render_mode", "not a robotics task", "the Fetch maze"],
)
def test_people_are_not_asked_about_pairs_the_page_cannot_draw(tmp_path, make_env, reason):
    """Refused at setup: the page would show two empty boxes, and the answers given to them would train the model."""
    env = make_env()
    for spec in (f"people:{tmp_path}", f"mixed:{tmp_path}:0.5"):
        with pytest.raises(ValueError, match=r"^preference_source sends pairs to people") as error:
            preference_source_from(spec, SCRIPT_LABELER, env)
        assert reason in str(error.value)
        assert f"it draws {DRAWN_ENVS}. Register the env id with gymnasium.register" in str(error.value)
        assert "or label with the script: preference_source=None" in str(error.value)
    assert not (tmp_path / "queue.json").exists()
    env.close()


def test_a_model_refuses_people_on_an_env_the_page_cannot_draw_before_it_trains(tmp_path):
    """The four-room maze made from its class, not its id: the page, which makes its env from the id, cannot draw it."""
    env = make_vec_env(lambda: TimeLimit(PointMazeFourRoomsEnv(), 20))
    for model_class in (DIPPER, PIPER, DPOFlat):
        with pytest.raises(ValueError, match=r"cannot draw the pairs of this env \(it has no registered id"):
            model = any_tiny_model(model_class, env, preference_source=f"people:{tmp_path}", max_episode_steps=20)
            model.learn(1)  # DPO-FLAT builds its labeller when learning starts, before the first step
    assert not (tmp_path / "queue.json").exists()
    env.close()


@pytest.mark.parametrize("env_id", ["PointMazeFourRooms-v0", "FetchPickAndPlace-v4"])
def test_people_label_the_envs_the_page_draws(tmp_path, env_id):
    env = make_vec_env(env_id)
    assert people(tmp_path, env).queue_info["env_id"] == env_id
    env.close()


# ---------------------------------------------------------------------------------------------------- the page beside training


@pytest.mark.parametrize(
    ("spec", "directory"),
    [
        ("people:logs/labels", "logs/labels"),
        ("mixed:logs/labels:0.3", "logs/labels"),
        ({"kind": "mixed", "directory": "d", "person_fraction": 0.5}, "d"),
        (QueuedPreferenceSource("q"), "q"),
        ("noisy:0.1", None),
        ("primitive", None),
        (None, None),
        (NoisyLabeler(0.2), None),
    ],
)
def test_the_label_queue_of_a_preference_source(spec, directory):
    assert label_queue_directory(spec) == directory


@pytest.mark.tools
@pytest.mark.parametrize("text", ["", "host:", "50OO", "localhost:70000", "-1"])
def test_a_bad_label_page_address_names_the_flag(text):
    with pytest.raises(ValueError, match="--label-page takes") as error:
        split_run_control(["--label-page", text])
    # The page is for this machine: its advice is an SSH tunnel, not serving on every interface.
    assert "forward the port over SSH" in str(error.value) and "0.0.0.0" not in str(error.value)


@pytest.mark.tools
def test_label_page_flag_parses_host_and_port():
    assert split_run_control(["--label-page", "5001", "--algo", "dipper"]) == (
        RunControl(label_page=("127.0.0.1", 5001)),
        ["--algo", "dipper"],
    )
    assert split_run_control(["--label-page", "0.0.0.0:0"])[0].label_page == ("0.0.0.0", 0)


JSON_HEADERS = {"Content-Type": "application/json"}


def zoo_train(tmp_path: Path, *params: str, label_page: str = "127.0.0.1:0") -> subprocess.Popen:
    command = [sys.executable, "-m", "sb3_dipper.zoo", "train", "--algo", "dipper", "--env", "PointMazeFourRooms-v0"]
    command += ["-f", str(tmp_path / "logs"), "--seed", "0", "-n", "200000", "--eval-freq", "-1", "--label-page", label_page]
    command += ["-params", "learning_starts:200", *params]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO)


@pytest.mark.tools
def test_training_serves_the_labelling_page_and_uses_its_labels(tmp_path):
    """``--label-page``: the page runs inside the training process; a label given there reaches that training."""
    directory = tmp_path / "labels"
    training = zoo_train(tmp_path, f"preference_source:'people:{directory}'", "n_preference_pairs:8")
    try:
        lines: list[str] = []
        assert training.stdout is not None
        for line in training.stdout:
            lines.append(line)
            if line.startswith("Labelling page of "):
                url = line.split(": ", 1)[1].strip() + "/"
                break
        else:
            pytest.fail("".join(lines[-40:]))
        pair_id = None
        for _ in range(600):  # training queues pairs once its first higher-level trajectories end
            claim = urllib.request.Request(url + "api/next", data=b'{"client": "test"}', headers=JSON_HEADERS)
            pair_id = json.loads(urllib.request.urlopen(claim, timeout=5).read())["pair_id"]
            if pair_id is not None:
                break
            time.sleep(0.2)
        assert pair_id is not None, "training queued no pair in 2 minutes"
        for side in ("left", "right"):  # the page shows both pictures before it can answer
            assert urllib.request.urlopen(f"{url}api/pair/{pair_id}/{side}.png", timeout=60).status == 200
        request = urllib.request.Request(
            url + "api/label",
            data=json.dumps({"pair_id": pair_id, "client": "test", "answer": "left"}).encode(),
            headers=JSON_HEADERS,
        )
        assert json.loads(urllib.request.urlopen(request, timeout=5).read())["ok"]
        queue = LabelQueue(directory)
        assert queue.answers().as_dict() == {pair_id: 1.0}
        # Training collects the label on its own (it never waits for it) and records the hand-over.
        for _ in range(600):
            if pair_id in queue.read_handed()["pair_id"].tolist():
                break
            time.sleep(0.2)
        handed = queue.read_handed()
        assert handed["pair_id"].tolist() == [pair_id] and handed["label"].tolist() == [1.0]
        assert handed["labeller"].tolist() == [PERSON]
    finally:
        training.kill()
        training.wait(timeout=30)


@pytest.mark.tools
def test_label_page_without_people_to_ask_is_refused_before_training(tmp_path):
    training = zoo_train(tmp_path, "n_preference_pairs:8")
    output, _ = training.communicate(timeout=300)
    assert training.returncode != 0
    assert "--label-page: DIPPER's preference_source sends no pairs to people" in output
    assert "total_timesteps" not in output  # refused before the first step


# ---------------------------------------------------------------------------------------------------- the page's defences


@pytest.fixture
def served(tmp_path, maze_env):
    """Three queued maze pairs and the page serving them on loopback from this process: ``(port, queue directory)``."""
    people(tmp_path, maze_env).label(random_pairs(3))
    server = serve_in_background(tmp_path, "127.0.0.1", 0)
    yield server.server_port, tmp_path
    server.shutdown()


def request_page(
    port: int, method: str, path: str, body: bytes | None = None, headers: dict[str, str] | None = None
) -> tuple[int, bytes]:
    """One request to the page over loopback (bounded by a timeout): its status and body."""
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        connection.request(method, path, body=body, headers={"Content-Type": "application/json", **(headers or {})})
        response = connection.getresponse()
        return response.status, response.read()
    finally:
        connection.close()


def wait_until_serving(server: subprocess.Popen, port: int, seconds: float = 180.0) -> int:
    """Wait until the page ``server`` started answers on ``port`` (importing the page's packages takes long on a busy
    machine); the status of its ``/api/status``. Fails if the server exits or does not answer in ``seconds``."""
    deadline = time.monotonic() + seconds
    while True:
        try:
            return request_page(port, "GET", "/api/status")[0]
        except OSError:
            assert server.poll() is None, f"the labelling page exited with {server.returncode}"
            assert time.monotonic() < deadline, f"the labelling page did not start in {seconds:.0f} s"
            time.sleep(0.2)


def look_at(port: int, pair_id: int) -> None:
    """Fetch both pictures of a pair, as the page does before the pair can be answered."""
    for side in ("left", "right"):
        status, png = request_page(port, "GET", f"/api/pair/{pair_id}/{side}.png")
        assert status == 200 and png.startswith(b"\x89PNG")


def label_body(pair_id: object = 0, client: str = "x", answer: object = "left") -> bytes:
    return json.dumps({"pair_id": pair_id, "client": client, "answer": answer}).encode()


def test_the_page_says_how_to_label(served):
    port, _ = served
    status, body = request_page(port, "GET", "/")
    page = " ".join(body.decode().split())  # the HTML's line breaks as spaces
    assert status == 200 and '<details id="how-to" open>' in page
    for how_to in (
        "<b>A pair</b> is two trajectories of the agent",
        "<kbd>s</kbd> skip",
        "subgoal (&times;, numbered in order)",
        "spends an option",
        "<b>A hindsight goal.</b>",
        "not the goal the agent was given, but a place one of the two trajectories reached",
        "so they may start at different places",
    ):
        assert how_to in page


def test_the_page_answers_only_requests_that_name_this_machine(served):
    """DNS rebinding: a page on evil.example, its name pointed at 127.0.0.1, sends Host: evil.example."""
    port, directory = served
    for method, path, body in [("POST", "/api/label", label_body()), ("GET", "/api/status", None), ("GET", "/", None)]:
        status, reply = request_page(port, method, path, body, {"Host": f"evil.example:{port}"})
        assert status == 400 and b"Unknown Host" in reply
    assert LabelQueue(directory).answers().pair_ids.tolist() == []
    for host in (f"localhost:{port}", f"127.0.0.1:{port}"):
        assert request_page(port, "GET", "/api/status", headers={"Host": host})[0] == 200
    look_at(port, 0)
    assert request_page(port, "POST", "/api/label", label_body(), {"Host": f"localhost:{port}"})[0] == 200


def test_other_sites_can_neither_claim_nor_label_pairs(served):
    port, directory = served
    # A claim is a POST: an <img src=".../api/next?client=..."> on another page claims nothing.
    assert request_page(port, "GET", "/api/next?client=img")[0] == 405
    assert LabellingServer(directory).claims.holder(0) is None
    own_origin = {"Origin": f"http://127.0.0.1:{port}", "Sec-Fetch-Site": "same-origin"}
    for refused in ({"Origin": "http://evil.example"}, {"Origin": "null"}, {"Sec-Fetch-Site": "cross-site"}):
        for path, body in [("/api/next", b'{"client": "evil"}'), ("/api/label", label_body(client="evil"))]:
            status, reply = request_page(port, "POST", path, body, refused)
            assert status == 403 and b"refused" in reply
        assert request_page(port, "GET", "/api/pair/0/left.png", headers=refused)[0] == 403
    assert LabelQueue(directory).answers().pair_ids.tolist() == []
    status, reply = request_page(port, "POST", "/api/next", b'{"client": "tab"}', own_origin)
    assert status == 200 and json.loads(reply)["pair_id"] == 0
    look_at(port, 0)
    assert request_page(port, "POST", "/api/label", label_body(client="tab"), own_origin)[0] == 200


def test_request_bodies_are_small_json_objects_with_integer_pair_ids(served):
    port, directory = served
    status, reply = request_page(port, "POST", "/api/label", b"x" * (MAX_BODY_BYTES + 1))
    assert status == 413 and "error" in json.loads(reply)
    for body in (b"[1, 2]", b'"left"', b"not json"):
        status, reply = request_page(port, "POST", "/api/label", body)
        assert status == 400 and "JSON object" in json.loads(reply)["error"]
    status, reply = request_page(port, "POST", "/api/label", label_body(pair_id=True))
    assert status == 400 and "pair_id (int)" in json.loads(reply)["error"]
    assert request_page(port, "POST", "/api/label", label_body(pair_id=1.0))[0] == 400
    # An answer that is no string (unhashable, so no key of ANSWERS) was a 500 with no message.
    status, reply = request_page(port, "POST", "/api/label", label_body(answer={}))
    assert status == 400 and "answer (one of" in json.loads(reply)["error"]
    assert LabelQueue(directory).answers().pair_ids.tolist() == []


def test_a_pair_is_answered_only_after_both_its_pictures_were_sent(served):
    port, directory = served
    status, reply = request_page(port, "POST", "/api/label", label_body(0))
    assert status == 409 and "Pair 0 was not shown" in json.loads(reply)["error"]
    assert request_page(port, "GET", "/api/pair/0/left.png")[0] == 200
    assert request_page(port, "POST", "/api/label", label_body(0))[0] == 409  # one side is not the pair
    assert request_page(port, "GET", "/api/pair/0/right.png")[0] == 200
    assert request_page(port, "POST", "/api/label", label_body(0))[0] == 200
    # A restarted page finds pair 1's pictures in images/, drawn before it started: they count once it sends them.
    look_at(port, 1)
    restarted = create_app(directory).test_client()
    answer = {"pair_id": 1, "client": "x", "answer": "right"}
    reply = restarted.post("/api/label", json=answer)
    assert reply.status_code == 409 and "Pair 1 was not shown" in reply.get_json()["error"]
    for side in ("left", "right"):
        assert restarted.get(f"/api/pair/1/{side}.png").status_code == 200
    assert restarted.post("/api/label", json=answer).status_code == 200
    assert LabelQueue(directory).answers().as_dict() == {0: 1.0, 1: 0.0}


def test_a_pair_the_page_cannot_draw_cannot_be_answered(tmp_path):
    """A queue that records no env: both pictures are errors, and no answer, not even a skip, is recorded."""
    people(tmp_path).label(random_pairs(1))
    page = create_app(tmp_path).test_client()
    for side in ("left", "right"):
        reply = page.get(f"/api/pair/0/{side}.png")
        assert reply.status_code == 500 and "does not say which env" in reply.get_json()["error"]
    for answer in ANSWERS:
        assert page.post("/api/label", json={"pair_id": 0, "client": "x", "answer": answer}).status_code == 409
    assert LabelQueue(tmp_path).answers().pair_ids.tolist() == []


def test_the_page_shows_why_a_picture_cannot_be_drawn_and_disables_the_answers(chromium, tmp_path):
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    people(tmp_path).label(random_pairs(1))
    server = serve_in_background(tmp_path, "127.0.0.1", 0)
    try:
        chromium.get(f"http://127.0.0.1:{server.server_port}/")
        message = WebDriverWait(chromium, 60).until(
            lambda browser: (
                "cannot be shown" in browser.find_element(By.ID, "message").text
                and browser.find_element(By.ID, "message").text
            )
        )
        assert "so the pair cannot be answered" in message and "does not say which env" in message
        assert not any(button.is_enabled() for button in chromium.find_elements(By.CSS_SELECTOR, "#buttons button"))
    finally:
        server.shutdown()


def test_a_reused_pair_id_never_gets_an_old_picture(tmp_path, maze_env):
    """A queue cleared by hand but for images/ gives ids from 0 again: the picture served is the new pair's."""
    people(tmp_path, maze_env).label(random_pairs(1, seed=0))
    running = create_app(tmp_path).test_client()
    old = running.get("/api/pair/0/left.png").data
    queue = LabelQueue(tmp_path)
    shutil.rmtree(queue.pairs_dir)
    people(tmp_path, maze_env).label(random_pairs(1, seed=1))
    assert queue.queued_ids() == [0]
    renderer = PairRenderer(queue.read_info())
    new = renderer.render(queue.read_pair(0), "left")
    renderer.close()
    assert new != old
    for page in (running, create_app(tmp_path).test_client()):  # the page that drew the old pair, and a restarted one
        assert page.get("/api/pair/0/left.png").data == new


def test_a_damaged_queue_file_reaches_the_page_as_its_message(served):
    """The page shows the server's error (its script retries); a damaged labels.npz was Werkzeug's bare 500 page."""
    port, directory = served
    queue = LabelQueue(directory)
    queue.record_answer(0, 1.0)
    save_npz(queue.labels_path, {**dict(np.load(queue.labels_path)), "label": np.array([2.0], np.float32)})
    status, reply = request_page(port, "POST", "/api/next", b'{"client": "tab"}')
    assert status == 500 and "labels.npz: label must hold 0, 0.5, 1 or NaN" in json.loads(reply)["error"]


def test_the_page_never_runs_in_debug_mode_whatever_the_environment_says(tmp_path):
    """FLASK_DEBUG, a .flaskenv in the working directory and a .env above it would turn on Werkzeug's debugger."""
    people(tmp_path / "labels").label(random_pairs(1))
    work = tmp_path / "work"
    work.mkdir()
    (tmp_path / ".env").write_text("FLASK_DEBUG=1\n")
    (work / ".flaskenv").write_text("FLASK_DEBUG=1\nFLASK_RUN_PORT=5001\n")
    port = free_port()
    server = subprocess.Popen(
        [sys.executable, "-m", "sb3_dipper.labelling.app", "--run", str(tmp_path / "labels"), "--port", str(port)],
        env={**os.environ, "FLASK_DEBUG": "1", "PYTHONPATH": str(REPO)},
        cwd=work,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        assert wait_until_serving(server, port) == 200
        status, reply = request_page(port, "GET", "/console")
        assert status == 404 and b"Werkzeug" not in reply
    finally:
        server.terminate()
        server.wait(timeout=10)
    assert create_app(tmp_path / "labels").debug is False
