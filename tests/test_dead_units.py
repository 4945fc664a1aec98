"""The dead-unit diagnostic of the lower level: ``train/low_actor_dead_units`` and ``train/low_critic_dead_units``."""

import os

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.logger import configure

from sb3_dipper.common.low_level import dead_unit_share, sac_dead_units
from tests.conftest import HIERARCHICAL_ALGORITHMS, short_maze, tiny_model


def two_layer_network() -> th.nn.Sequential:
    first, second = th.nn.Linear(2, 3), th.nn.Linear(3, 2)
    with th.no_grad():
        first.weight.copy_(th.tensor([[1.0, 0.0], [0.0, 1.0], [-1.0, -1.0]]))
        first.bias.zero_()
        second.weight.copy_(th.tensor([[1.0, 1.0, 0.0], [-1.0, -1.0, 0.0]]))
        second.bias.zero_()
    return th.nn.Sequential(first, th.nn.ReLU(), second, th.nn.ReLU())


def test_dead_unit_share_is_the_largest_share_of_units_silent_on_every_input():
    inputs = th.tensor([[1.0, 0.0], [0.0, 2.0]])
    # First layer: units 1 and 2 fire on some row, unit 3 (-x - y) on none: 1/3 dead.
    # Second layer: unit 1 (x + y) fires, unit 2 (-(x + y)) never: 1/2 dead. The largest is 1/2.
    assert dead_unit_share(two_layer_network(), inputs) == pytest.approx(0.5)
    # On inputs where every first-layer unit is silent, the whole layer is dead.
    assert dead_unit_share(two_layer_network()[:2], th.tensor([[0.0, 0.0]])) == pytest.approx(1.0)
    assert dead_unit_share(th.nn.Sequential(th.nn.Linear(2, 2), th.nn.Tanh()), inputs) is None


def test_a_lower_actor_with_a_dead_layer_is_reported_and_reading_draws_no_random_numbers():
    model = tiny_model(HIERARCHICAL_ALGORITHMS[0], short_maze())
    assert sac_dead_units(model.lower) == {}  # nothing stored yet
    model.learn(60)
    rng_states = th.get_rng_state(), np.random.get_state()[1].copy()
    healthy = sac_dead_units(model.lower)
    assert th.equal(th.get_rng_state(), rng_states[0]) and np.array_equal(np.random.get_state()[1], rng_states[1])
    assert set(healthy) == {"actor", "critic"} and healthy["actor"] < 1.0
    with th.no_grad():
        model.lower.actor.latent_pi[0].bias.fill_(-1e6)  # every unit of the first layer silent on every input
    assert sac_dead_units(model.lower)["actor"] == 1.0


@pytest.mark.parametrize("model_class", HIERARCHICAL_ALGORITHMS)
def test_every_learned_lower_level_logs_its_dead_units(model_class, tmp_path):
    model = tiny_model(model_class, short_maze())
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(200, log_interval=1)
    header = open(os.path.join(tmp_path, "progress.csv")).readline().strip().split(",")
    assert {"train/low_actor_dead_units", "train/low_critic_dead_units"} <= set(header)
