"""The lower level's acting average (``low_policy_kwargs=dict(acting_tau=...)``): it follows the trained actor by one
Polyak step per actor update, it is what the lower level acts with, and it is saved with the model."""

import numpy as np
import pytest
import torch as th

from sb3_dipper import DIPPER
from sb3_dipper.common.low_level import LowerSACPolicy
from tests.conftest import HIERARCHICAL_ALGORITHMS, short_maze, tiny_model

TAU = 0.1


def averaging_model(model_class, acting_tau: float = TAU, **overrides):
    low_policy_kwargs = dict(net_arch=[16], acting_tau=acting_tau)
    return tiny_model(model_class, short_maze(n_envs=2), low_policy_kwargs=low_policy_kwargs, **overrides)


def parameters(module: th.nn.Module) -> list[th.Tensor]:
    return [parameter.detach().clone() for parameter in module.parameters()]


@pytest.mark.parametrize("model_class", HIERARCHICAL_ALGORITHMS)
def test_the_average_takes_one_polyak_step_after_each_actor_update(model_class):
    model = averaging_model(model_class)
    model.learn(60)
    policy = model.lower.policy
    assert isinstance(policy, LowerSACPolicy)
    averaged_before = parameters(policy.averaged_actor)
    model.lower.train(gradient_steps=1, batch_size=16)
    actor_after = parameters(policy.actor)
    for before, actor, averaged in zip(averaged_before, actor_after, policy.averaged_actor.parameters(), strict=True):
        th.testing.assert_close(averaged, (1 - TAU) * before + TAU * actor)
    lagging = [not th.equal(a, b) for a, b in zip(actor_after, policy.averaged_actor.parameters(), strict=True)]
    assert any(lagging), "the average lags the actor"


def test_without_the_switch_the_lower_policy_keeps_no_average():
    model = tiny_model(DIPPER, short_maze(n_envs=2))
    model.learn(60)
    assert model.lower.policy.averaged_actor is None
    assert not any(key.startswith("averaged_actor") for key in model.lower.policy.state_dict())  # older files load


def zero_mean_head(actor: th.nn.Module) -> None:
    with th.no_grad():
        actor.mu.weight.zero_()
        actor.mu.bias.zero_()


def test_the_lower_level_acts_with_the_average_while_collecting_predicting_and_exported():
    model = averaging_model(DIPPER, planning="off")
    model.learn(60)
    zero_mean_head(model.lower.policy.averaged_actor)  # the average acts with a tanh(0) mean: the action range's centre
    centre = model.lower.policy.unscale_action(np.zeros((2, model.action_space.shape[0]), dtype=np.float32))
    low_obs = {key: value[-2:, 0] for key, value in model.lower.replay_buffer.observations.items()}

    np.testing.assert_allclose(model.low_level.act(low_obs, deterministic=True), centre, atol=1e-6)
    with th.no_grad():
        trained = model.lower.actor(model.low_level.tensor_obs(low_obs), deterministic=True).numpy()
    assert not np.allclose(trained, 0.0, atol=1e-3), "the trained actor would act otherwise"

    observation = model.env.reset()
    action, _ = model.predict(observation, deterministic=True)
    np.testing.assert_allclose(action, centre, atol=1e-6)
    exported, _ = model.export_policy().predict(observation, deterministic=True)
    np.testing.assert_allclose(exported, centre, atol=1e-6)


def test_save_and_load_keep_the_average(tmp_path):
    model = averaging_model(DIPPER)
    model.learn(60)
    model.save(tmp_path / "model.zip")
    loaded = DIPPER.load(tmp_path / "model.zip", env=short_maze(n_envs=2))
    assert loaded.lower.policy.acting_tau == TAU
    saved, restored = model.lower.policy, loaded.lower.policy
    for before, after in zip(saved.averaged_actor.parameters(), restored.averaged_actor.parameters(), strict=True):
        assert th.equal(before, after)
    pairs = zip(restored.actor.parameters(), restored.averaged_actor.parameters(), strict=True)
    lagging = [not th.equal(actor, averaged) for actor, averaged in pairs]
    assert any(lagging), "the average is restored as saved, not copied from the actor"


@pytest.mark.parametrize("acting_tau", [0.0, 1.5])
def test_an_acting_tau_outside_zero_to_one_is_refused_at_construction(acting_tau):
    with pytest.raises(ValueError, match=r"low_policy_kwargs\['acting_tau'\]"):
        averaging_model(DIPPER, acting_tau=acting_tau)
