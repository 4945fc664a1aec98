"""SAGA: the discriminator and adversarial losses by hand, relabelled subgoals, the actor's extra gradient, its variant
without the state, a learning check (its runs, saving and seeding: tests/test_run.py, tests/test_save_load.py)."""

import math
import os

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import configure

from sb3_dipper.saga import SAGA, AdversarialSAC
from sb3_dipper.saga.saga import adversarial_loss, discriminator_loss
from tests.conftest import short_maze
from tests.test_save_load import rollout_actions

TINY_SAGA = dict(
    option_steps=5,
    learning_starts=40,
    buffer_size=2000,
    batch_size=16,
    low_policy_kwargs=dict(net_arch=[16]),
    seed=0,
    high_batch_size=16,
    high_buffer_size=1000,
    policy_kwargs=dict(net_arch=[16]),
    discriminator_kwargs=dict(net_arch=[16]),
    adversarial_coef=0.1,
)


def tiny_saga(env, **overrides) -> SAGA:
    return SAGA("MultiInputPolicy", env, **{**TINY_SAGA, **overrides})


def softplus(value: float) -> float:
    return math.log1p(math.exp(value))


# ---------------------------------------------------------------------------------------------------- the losses by hand


def test_discriminator_loss_by_hand():
    # Relabelled logits (2, 0) are real: -log sigma(l) = softplus(-l); generated (-1, 1) are fake: softplus(l).
    loss = discriminator_loss(th.tensor([2.0, 0.0]), th.tensor([-1.0, 1.0]))
    real = (softplus(-2.0) + softplus(0.0)) / 2  # (0.126928 + 0.693147) / 2 = 0.410038
    fake = (softplus(-1.0) + softplus(1.0)) / 2  # (0.313262 + 1.313262) / 2 = 0.813262
    assert loss.item() == pytest.approx(0.5 * (real + fake), abs=1e-6)  # 0.611650


def test_a_perfect_discriminator_has_a_small_loss_and_a_confused_one_log_two():
    assert discriminator_loss(th.tensor([20.0]), th.tensor([-20.0])).item() < 1e-8
    assert discriminator_loss(th.zeros(3), th.zeros(3)).item() == pytest.approx(math.log(2), abs=1e-6)


def test_adversarial_loss_by_hand_and_its_gradient_raises_the_discriminators_score():
    logits = th.tensor([-1.0, 1.0], requires_grad=True)
    loss = adversarial_loss(logits)
    assert loss.item() == pytest.approx((softplus(1.0) + softplus(-1.0)) / 2, abs=1e-6)  # 0.813262
    loss.backward()
    # d/dl softplus(-l) / N = (sigma(l) - 1) / N: (0.268941 - 1) / 2 and (0.731059 - 1) / 2.
    assert logits.grad.tolist() == pytest.approx([-0.365529, -0.134471], abs=1e-6)


# ---------------------------------------------------------------------------------------------------- the mechanism


def add_episode(model: SAGA, starts: list[tuple[float, float]], ends: list[tuple[float, float]]) -> None:
    """Store one finished higher-level episode whose options start at ``starts`` and reach ``ends`` (x, y positions)."""
    buffer = model.higher.replay_buffer
    goal = np.array([[3.0, 3.0]])
    for index, (start, end) in enumerate(zip(starts, ends, strict=True)):
        obs = {"observation": np.array([[*start, 0.0, 0.0]]), "achieved_goal": np.array([start]), "desired_goal": goal}
        next_obs = {"observation": np.array([[*end, 0.0, 0.0]]), "achieved_goal": np.array([end]), "desired_goal": goal}
        done = np.array([index == len(starts) - 1])
        buffer.add(obs, next_obs, np.zeros((1, 2)), np.array([-1.0]), done, [{}])


def test_relabelled_subgoals_are_where_each_option_ended_paired_with_its_start(maze_env):
    model = tiny_saga(maze_env)
    # The maze's subgoal box is [-3.5, 3.5]^2: (1.75, -3.5) is (0.5, -1) in the higher level's unit coordinates,
    # and (0, 7) lies outside the box, clipped to (0, 1).
    add_episode(model, starts=[(0.0, 0.0), (1.75, -3.5)], ends=[(1.75, -3.5), (0.0, 7.0)])
    observations, relabelled = model._sample_options(32)
    starts = observations["achieved_goal"].numpy()
    expected = np.where(starts[:, :1] == 0.0, [[0.5, -1.0]], [[0.0, 1.0]])
    np.testing.assert_allclose(relabelled.numpy(), expected, atol=1e-6)
    assert {tuple(start) for start in starts} == {(0.0, 0.0), (1.75, -3.5)}

    states = model._discriminator_states(observations)
    np.testing.assert_allclose(states.numpy(), np.concatenate([observations["observation"], starts], axis=1))
    assert tiny_saga(maze_env, state_conditioned=False)._discriminator_states(observations) is None


def test_the_adversarial_term_adds_exactly_its_gradient_to_the_actor_step(maze_env):
    model = tiny_saga(maze_env)
    model.learn(100)
    assert model.higher.actor_loss_term == model._adversarial_term
    sac: AdversarialSAC = model.higher
    sac.lr_schedule = lambda _: 0.0  # no optimizer moves a parameter, so both runs below start from the same networks
    captured: list[list[th.Tensor]] = []
    sac.actor.optimizer.register_step_pre_hook(
        lambda *_: captured.append([parameter.grad.clone() for parameter in sac.actor.parameters()])
    )

    def actor_gradient(term) -> list[th.Tensor]:
        sac.actor_loss_term = term
        np.random.seed(0)  # the same SAC batch
        th.manual_seed(0)  # the same action samples
        sac.train(gradient_steps=1, batch_size=16)
        return captured.pop()

    # The term 0.5 * (sum of the actor's parameters) has gradient 0.5 for every parameter.
    with_term = actor_gradient(lambda: 0.5 * sum(parameter.sum() for parameter in sac.actor.parameters()))
    without_term = actor_gradient(None)
    for gradient, reference in zip(with_term, without_term, strict=True):
        assert th.allclose(gradient - reference, th.full_like(gradient, 0.5), atol=1e-6)


def test_no_adversarial_term_at_zero_weight(maze_env):
    assert tiny_saga(maze_env, adversarial_coef=0.0).higher.actor_loss_term is None
    with pytest.raises(ValueError, match="adversarial_coef"):
        tiny_saga(maze_env, adversarial_coef=-1.0)


# ---------------------------------------------------------------------------------------------------- runs and saving


def test_a_discriminator_without_the_state_learns_logs_and_reloads(maze_env, tmp_path):
    model = tiny_saga(maze_env, state_conditioned=False)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(200, log_interval=1)
    header = open(os.path.join(tmp_path, "progress.csv")).readline().strip().split(",")
    expected = {"train/high_disc_loss", "train/high_adversarial_loss", "train/high_actor_loss", "train/low_actor_loss"}
    assert expected <= set(header)

    model.save(tmp_path / "model")
    loaded = SAGA.load(tmp_path / "model", env=None)
    assert not loaded.state_conditioned
    for name, tensor in model.discriminator.state_dict().items():
        assert th.equal(tensor, loaded.discriminator.state_dict()[name]), name
    np.testing.assert_array_equal(rollout_actions(model, short_maze(seed=4)), rollout_actions(loaded, short_maze(seed=4)))


def test_a_resumed_model_keeps_the_adversarial_term_in_its_higher_actor_step(tmp_path):
    tiny_saga(short_maze(n_envs=2)).save(tmp_path / "model")
    loaded_with_env = SAGA.load(tmp_path / "model", env=short_maze(n_envs=2, seed=1))
    given_env_later = SAGA.load(tmp_path / "model")
    given_env_later.set_env(short_maze(n_envs=2, seed=1))
    for resumed in (loaded_with_env, given_env_later):
        resumed.learn(60, reset_num_timesteps=False)
        assert resumed.num_timesteps == 60 and resumed.higher.actor_loss_term == resumed._adversarial_term


# ---------------------------------------------------------------------------------------------------- learning


def subgoal_statistics(model: SAGA) -> tuple[float, float]:
    """Mean distance (unit coordinates) from an option's start to the higher policy's subgoal there, and D's accuracy."""
    observations, relabelled = model._sample_options(2000)
    start = th.as_tensor(model.subgoal_space.to_unit(observations["achieved_goal"].numpy()))
    states = model._discriminator_states(observations)
    with th.no_grad():
        deterministic = model.higher.actor(observations, deterministic=True)
        generated, _ = model.higher.actor.action_log_prob(observations)
        real_right = (model.discriminator(states, relabelled) > 0).float().mean()
        fake_right = (model.discriminator(states, generated) < 0).float().mean()
    return (deterministic - start).norm(dim=1).mean().item(), 0.5 * (real_right + fake_right).item()


def test_the_adversarial_term_pulls_subgoals_toward_what_the_lower_level_reaches():
    """1,500 steps on the maze: the discriminator separates reached from generated subgoals (measured: 0.92 accuracy
    without the adversarial term), and the adversarial term brings the generated subgoals near the options' starts,
    where the reached ones are (measured: 0.30 from the start against 0.92-0.94 without it; reached ones: 0.07)."""
    statistics = {}
    for coef in (0.0, 1.0):
        model = SAGA(
            "MultiInputPolicy",
            make_vec_env("sb3_dipper:PointMazeFourRooms-v0", n_envs=2, seed=1, env_kwargs=dict(max_episode_steps=60)),
            option_steps=10,
            learning_starts=600,
            buffer_size=20_000,
            batch_size=64,
            train_freq=4,
            low_policy_kwargs=dict(net_arch=[64, 64]),
            high_batch_size=64,
            high_gradient_steps=4,
            policy_kwargs=dict(net_arch=[64, 64]),
            adversarial_coef=coef,
            discriminator_learning_rate=1e-3,
            seed=1,
        )
        model.learn(1500)
        statistics[coef] = subgoal_statistics(model)
    (distance_without, accuracy_without), (distance_with, _) = statistics[0.0], statistics[1.0]
    assert accuracy_without >= 0.75
    assert distance_with < 0.5 * distance_without
