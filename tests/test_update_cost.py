"""The cheaper training updates compute what the straightforward ones compute.

Each test runs the library's update on a fixed batch and the straightforward computation (the code before the update
was made cheaper, restated here) on the same batch, weights and random draws, and compares losses and gradients.
"""

import argparse
import copy

import numpy as np
import pytest
import torch as th
import torch.nn.functional as F
from stable_baselines3.common.utils import obs_as_tensor

from sb3_dipper import DIPPER
from sb3_dipper.common.imitation import DemoSAC, behaviour_cloning_loss, q_filter_mask
from sb3_dipper.common.losses import dipper_loss, preferred_nll
from sb3_dipper.common.low_level import clipped_soft_target, sac_value_gap, step_entropy_coefficient
from sb3_dipper.common.preferences import flat_pair_observations
from sb3_dipper.envs.demos import expert_demonstrations
from tests.conftest import short_maze, tiny_model
from zoo_scripts.benchmarking import profile as benchmark

TOLERANCE = 1e-5


@pytest.fixture(scope="module")
def trained_dipper(tmp_path_factory):
    """A tiny DIPPER with demonstrations, a filled lower buffer and labelled pairs with padded (truncated) steps."""
    demos = tmp_path_factory.mktemp("demos") / "maze.npz"
    expert_demonstrations("PointMazeFourRooms-v0", n_episodes=1, seed=0).save(demos)
    model = tiny_model(
        DIPPER,
        short_maze(),
        demo_kwargs=dict(demo_path=str(demos), n_demos=1, demo_share=0.25),
        switch_kwargs=dict(nll_coef=1.0, hindsight_actions=True, truncate_at_goal=True),
    )
    model.learn(300)
    assert len(model.preferences) > 0
    return model


def gradients(module: th.nn.Module) -> list[th.Tensor]:
    return [parameter.grad.clone() for parameter in module.parameters()]


def assert_all_close(actual: list[th.Tensor], expected: list[th.Tensor]) -> None:
    assert len(actual) == len(expected)
    for got, want in zip(actual, expected, strict=True):
        th.testing.assert_close(got, want, atol=TOLERANCE, rtol=TOLERANCE)


def straightforward_demo_sac_step(sac: DemoSAC, batch, n_demo: int) -> dict[str, float]:
    """One gradient step of DemoSAC as first written: a second actor pass for the demo steps' deterministic actions, two
    Q-filter passes, and the actor loss backpropagated through the (trainable) critic."""
    actions_pi, log_prob = sac.actor.action_log_prob(batch.observations)
    log_prob = log_prob.reshape(-1, 1)
    ent_coef = step_entropy_coefficient(sac, log_prob)
    with th.no_grad():
        next_actions, next_log_prob = sac.actor.action_log_prob(batch.next_observations)
        next_q = th.cat(sac.critic_target(batch.next_observations, next_actions), dim=1).min(dim=1, keepdim=True).values
        bounds = sac.target_q_bounds or (-np.inf, np.inf)
        target_q = clipped_soft_target(
            batch.rewards, batch.dones, next_q, next_log_prob.reshape(-1, 1), ent_coef, sac.gamma, bounds
        )
    current_q = sac.critic(batch.observations, batch.actions)
    critic_loss = 0.5 * sum(F.mse_loss(q, target_q) for q in current_q)
    sac.critic.optimizer.zero_grad()
    critic_loss.backward()
    sac.critic.optimizer.step()

    min_q_pi = th.cat(sac.critic(batch.observations, actions_pi), dim=1).min(dim=1, keepdim=True).values
    sac_loss = (ent_coef * log_prob - min_q_pi).mean()
    demo_obs = {key: value[-n_demo:] for key, value in batch.observations.items()}
    demo_actions = batch.actions[-n_demo:]
    policy_actions = sac.actor(demo_obs, deterministic=True)
    with th.no_grad():
        demo_values = sac.critic.q1_forward(demo_obs, demo_actions)
        policy_values = sac.critic.q1_forward(demo_obs, policy_actions)
        keep = (demo_values > policy_values).float().reshape(-1) if sac.q_filter else th.ones(n_demo)
    bc_loss = behaviour_cloning_loss(policy_actions, demo_actions, keep)
    actor_loss = sac.rl_coef * sac_loss + sac.bc_coef * bc_loss
    sac.actor.optimizer.zero_grad()
    actor_loss.backward()
    sac.actor.optimizer.step()
    return dict(
        critic_loss=critic_loss.item(), actor_loss=actor_loss.item(), bc_loss=bc_loss.item(), q_filter_kept=keep.mean().item()
    )


@pytest.mark.parametrize("q_filter", [True, False])
def test_demo_sac_step_equals_the_straightforward_step(trained_dipper, monkeypatch, q_filter):
    """One actor pass for SAC's and the cloned actions, one Q-filter pass, the Q-networks frozen for the actor loss:
    same losses, same actor gradients, same critic update as the straightforward step on the same batch and noise.
    Without the Q-filter every demo step is cloned, so the cloning gradient is surely part of the comparison."""
    sac = trained_dipper.lower
    monkeypatch.setattr(sac, "q_filter", q_filter)
    n_demo = max(1, round(sac.demo_share * sac.batch_size))
    th.manual_seed(0)
    batch = sac._mixed_batch(sac.batch_size - n_demo, n_demo)
    monkeypatch.setattr(sac, "_mixed_batch", lambda n_replay, n_demo: batch)
    # target_update_interval = 1: the polyak update follows the step in both versions; compare before it.
    monkeypatch.setattr(sac, "target_update_interval", 10**9)
    optimizers = (sac.actor.optimizer, sac.critic.optimizer, sac.ent_coef_optimizer)
    start = copy.deepcopy(([optimizer.state_dict() for optimizer in optimizers], sac.policy.state_dict(), sac.log_ent_coef))

    th.manual_seed(1)
    expected = straightforward_demo_sac_step(sac, batch, n_demo)
    expected_actor_gradients = gradients(sac.actor)
    expected_weights = copy.deepcopy(sac.policy.state_dict())

    for optimizer, state in zip(optimizers, start[0], strict=True):
        optimizer.load_state_dict(state)
    sac.policy.load_state_dict(start[1])
    sac.log_ent_coef.data.copy_(start[2])
    th.manual_seed(1)
    sac.train(1, sac.batch_size)
    logged = trained_dipper.logger.name_to_value
    for key, value in expected.items():
        assert logged[f"train/low_{key}"] == pytest.approx(value, abs=TOLERANCE), key
    assert q_filter or expected["bc_loss"] > 0.0
    assert_all_close(gradients(sac.actor), expected_actor_gradients)
    assert_all_close(list(sac.policy.state_dict().values()), list(expected_weights.values()))
    # The Q-networks' weight gradients of the actor loss are no longer computed: their gradients are the critic loss's.
    assert all(parameter.requires_grad for parameter in sac.critic.parameters())


def test_one_pass_q_filter_equals_two_passes(trained_dipper):
    critic = trained_dipper.lower.critic
    generator = th.Generator().manual_seed(0)
    observations = {key: th.randn(12, *space.shape, generator=generator) for key, space in critic.observation_space.items()}
    demo_actions, policy_actions = th.rand(2, 12, 2, generator=generator) * 2.0 - 1.0
    with th.no_grad():
        expected = (critic.q1_forward(observations, demo_actions) > critic.q1_forward(observations, policy_actions)).float()
    assert th.equal(q_filter_mask(critic, observations, demo_actions, policy_actions), expected.reshape(-1))


def test_higher_update_on_real_steps_equals_the_padded_update(trained_dipper, monkeypatch):
    """Log-probabilities and the lower value gaps on the real steps only: the same DIPPER loss, preferred-side NLL,
    value gap and policy gradient as the straightforward update over every (padded) step of the pairs."""
    model = trained_dipper
    with th.no_grad():
        for parameter in model._value_snapshot.parameters():
            parameter.add_(0.1 * th.randn_like(parameter))
    pairs = model.preferences.sample(model.pairs_per_batch, np.random.default_rng(0))
    assert 0 < pairs.mask.sum() < pairs.mask.size, "the pairs have padded steps"
    monkeypatch.setattr(model.preferences, "sample", lambda n_pairs, rng: pairs)
    start = copy.deepcopy((model.policy.state_dict(), model.policy.actor.optimizer.state_dict()))

    flat_obs = obs_as_tensor(flat_pair_observations(pairs), model.device)
    actions = th.as_tensor(pairs.reached_actions, device=model.device)
    mask, labels = th.as_tensor(pairs.mask), th.as_tensor(pairs.labels)
    log_probs = model.policy.log_prob(flat_obs, actions.reshape(-1, actions.shape[-1])).reshape(mask.shape)
    th.manual_seed(3)
    with th.no_grad():
        low_obs = model._pair_low_obs(pairs, pairs.reached_actions)
        gaps = sac_value_gap(model.lower, model._value_snapshot, low_obs).reshape(mask.shape)
    dpo, _ = dipper_loss(log_probs, mask, labels, model.beta, model._reference_log_prob, gaps, model.value_reg_coef)
    nll = preferred_nll(log_probs, mask, labels)
    model.policy.actor.optimizer.zero_grad()
    (dpo + model.switch_kwargs["nll_coef"] * nll).backward()
    expected_gradients = gradients(model.policy.actor)
    expected_gap = ((gaps * mask).sum() / mask.sum()).item()

    model.policy.load_state_dict(start[0])
    model.policy.actor.optimizer.load_state_dict(start[1])
    th.manual_seed(3)
    model._train_high_level()
    logged = model.logger.name_to_value
    assert logged["train/high_dpo_loss"] == pytest.approx(dpo.item(), abs=TOLERANCE)
    assert logged["train/high_nll"] == pytest.approx(nll.item(), abs=TOLERANCE)
    assert logged["train/high_value_gap"] == pytest.approx(expected_gap, abs=TOLERANCE) and expected_gap != 0.0
    assert_all_close(gradients(model.policy.actor), expected_gradients)


def test_value_gaps_on_real_steps_keep_the_random_stream_of_every_step(trained_dipper):
    """The lower action sample of the value gaps draws noise for the padded steps too: the gaps at the real steps are
    those of evaluating every step and the random numbers drawn afterwards are exactly the same, so seeded runs repeat
    up to float rounding."""
    model = trained_dipper
    pairs = model.preferences.sample(model.pairs_per_batch, np.random.default_rng(1))
    mask = th.as_tensor(pairs.mask)
    assert 0 < pairs.mask.sum() < pairs.mask.size, "the pairs have padded steps"
    th.manual_seed(4)
    with th.no_grad():
        low_obs = model._pair_low_obs(pairs, model._pair_actions(pairs))
        every_step = sac_value_gap(model.lower, model._value_snapshot, low_obs).reshape(mask.shape)
    next_draw = th.rand(4)
    th.manual_seed(4)
    real_steps = model._value_gaps(pairs, mask)
    th.testing.assert_close(real_steps[mask], every_step[mask], atol=TOLERANCE, rtol=TOLERANCE)
    assert th.equal(real_steps[~mask], th.zeros(int((~mask).sum())))
    assert th.equal(th.rand(4), next_draw)


@pytest.mark.tools
def test_the_updates_benchmark_prints_ratios_to_sb3_sac(trained_dipper, monkeypatch, capsys):
    # The run's budget, which the warm-up trains within.
    monkeypatch.setattr(benchmark, "make_model", lambda algo, env_id, seed, overrides=None: (trained_dipper, None, 10**6))
    benchmark.run_updates(argparse.Namespace(env="PointMazeFourRooms-v0", warmup=20, updates=2, repeats=1))
    rows = [line.split(" | ") for line in capsys.readouterr().out.splitlines() if line.startswith("| ") and "---" not in line]
    assert [row[0] for row in rows[1:]] == [
        "| SB3 SAC.train, 1 gradient step",
        "| DemoSAC.train, 1 gradient step",
        "| DIPPER higher-level update",
    ]
    assert rows[1][2] == "1.00 |" and all(float(row[1]) > 0.0 for row in rows[1:])
