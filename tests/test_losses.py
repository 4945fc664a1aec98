"""The pure loss functions against values computed by hand."""

import math

import pytest
import torch as th
from stable_baselines3.common.distributions import SquashedDiagGaussianDistribution

from sb3_dipper.common.losses import (
    anchor_penalty,
    at_real_steps,
    dipper_logits,
    dipper_loss,
    preference_accuracy,
    preference_loss,
    preferred_nll,
    squashed_gaussian_log_prob,
    tie_share,
    uniform_log_prob,
)


def log_sigmoid(value: float) -> float:
    return -math.log1p(math.exp(-value))


def test_squashed_log_prob_of_zero_action_is_standard_normal_density():
    log_prob = squashed_gaussian_log_prob(th.zeros(1, 2), th.zeros(1, 2), th.zeros(1, 2))
    assert log_prob.item() == pytest.approx(-math.log(2 * math.pi) - 2e-6, abs=1e-6)


def test_squashed_log_prob_by_hand():
    # u = 0.5, x = atanh(0.5) = 0.549306; N(x; 0.2, 0.5): -0.5 * (0.698612)^2 - log 0.5 - 0.5 log 2 pi = -0.469821;
    # Jacobian: log(1 - 0.25) = -0.287682, so log p(u) = -0.469821 + 0.287682 = -0.182139.
    log_prob = squashed_gaussian_log_prob(th.tensor([[0.2]]), th.tensor([[math.log(0.5)]]), th.tensor([[0.5]]))
    assert log_prob.item() == pytest.approx(-0.182139, abs=1e-5)


def test_squashed_log_prob_matches_sb3_distribution():
    mean, log_std = th.tensor([[0.3, -1.2, 0.0]]), th.tensor([[-0.5, 0.2, -2.0]])
    actions = th.tensor([[0.9, -0.99, 0.1]])
    distribution = SquashedDiagGaussianDistribution(3).proba_distribution(mean, log_std)
    assert squashed_gaussian_log_prob(mean, log_std, actions).item() == pytest.approx(
        distribution.log_prob(actions).item(), rel=1e-4
    )


def test_boundary_actions_keep_a_finite_log_prob():
    log_prob = squashed_gaussian_log_prob(th.zeros(1, 2), th.zeros(1, 2), th.tensor([[1.0, -1.0]]))
    assert th.isfinite(log_prob).all()


def test_uniform_reference_density():
    assert uniform_log_prob(3) == pytest.approx(-3 * math.log(2))


# Pair of two-step trajectories: sum log pi(tau^1) = -3, sum log pi(tau^2) = -4, beta = 0.5, so z = 0.5.
LOG_PROBS = th.tensor([[[-1.0, -2.0]], [[-3.0, -1.0]]])
FULL_MASK = th.ones(2, 1, 2, dtype=th.bool)


@pytest.mark.parametrize(
    "label, expected",
    [
        (1.0, -log_sigmoid(0.5)),  # tau^1 preferred: 0.474077
        (0.0, -log_sigmoid(-0.5)),  # tau^2 preferred: 0.974077
        (0.5, -0.5 * log_sigmoid(0.5) - 0.5 * log_sigmoid(-0.5)),  # tie: 0.724077
    ],
)
def test_dipper_loss_preferred_dispreferred_and_tie(label, expected):
    loss, logits = dipper_loss(LOG_PROBS, FULL_MASK, th.tensor([label]), beta=0.5)
    assert logits.item() == pytest.approx(0.5)
    assert loss.item() == pytest.approx(expected, abs=1e-6)


def test_value_term_sign():
    # V^L - V^L_m sums to 0.3 on tau^1 and 0.5 on tau^2; with lambda = 2: z = 0.5 - 2 * (0.3 - 0.5) = 0.9.
    gaps = th.tensor([[[0.2, 0.1]], [[0.0, 0.5]]])
    logits = dipper_logits(LOG_PROBS, FULL_MASK, beta=0.5, value_gaps=gaps, value_reg_coef=2.0)
    assert logits.item() == pytest.approx(0.9)
    # A larger gap on the preferred side lowers z, so the loss of preferring tau^1 grows.
    larger_gap = dipper_logits(
        LOG_PROBS, FULL_MASK, beta=0.5, value_gaps=gaps + th.tensor([[[1.0, 0.0]], [[0.0, 0.0]]]), value_reg_coef=2.0
    )
    assert larger_gap.item() == pytest.approx(0.9 - 2.0)


def test_value_terms_carry_no_gradient():
    gaps = th.tensor([[[0.2, 0.1]], [[0.0, 0.5]]], requires_grad=True)
    log_probs = LOG_PROBS.clone().requires_grad_(True)
    loss, _ = dipper_loss(log_probs, FULL_MASK, th.tensor([1.0]), beta=0.5, value_gaps=gaps, value_reg_coef=1.0)
    loss.backward()
    assert gaps.grad is None
    assert log_probs.grad is not None


def test_lambda_zero_is_plain_token_level_dpo():
    gaps = th.tensor([[[5.0, 1.0]], [[-3.0, 2.0]]])
    labels = th.tensor([1.0])
    loss, _ = dipper_loss(LOG_PROBS, FULL_MASK, labels, beta=0.5, value_gaps=gaps, value_reg_coef=0.0)
    plain_dpo = -th.nn.functional.logsigmoid(0.5 * LOG_PROBS[0].sum() - 0.5 * LOG_PROBS[1].sum())
    assert loss.item() == pytest.approx(plain_dpo.item())


def test_reference_cancels_for_equal_lengths_but_not_for_unequal():
    reference = uniform_log_prob(2)
    assert dipper_logits(LOG_PROBS, FULL_MASK, 0.5, reference).item() == pytest.approx(0.5)
    # tau^2 has one real step: z = 0.5 * [(-3 - 2r) - (-3 - r)] = -0.5 r = 0.693147 for r = -2 log 2.
    mask = th.tensor([[[True, True]], [[True, False]]])
    assert dipper_logits(LOG_PROBS, mask, 0.5, reference).item() == pytest.approx(math.log(2))


def test_preference_loss_is_binary_cross_entropy_with_soft_labels():
    logits, labels = th.tensor([2.0, -1.0]), th.tensor([1.0, 0.5])
    expected = (-log_sigmoid(2.0) + (-0.5 * log_sigmoid(-1.0) - 0.5 * log_sigmoid(1.0))) / 2
    assert preference_loss(logits, labels).item() == pytest.approx(expected)


def test_label_smoothing_takes_each_strict_label_as_flipped_with_probability_epsilon():
    logits, labels = th.tensor([2.0, -1.0]), th.tensor([1.0, 0.5])
    # Label 1 becomes 0.9; the tie stays 0.5.
    expected = (-(0.9 * log_sigmoid(2.0) + 0.1 * log_sigmoid(-2.0)) - 0.5 * log_sigmoid(-1.0) - 0.5 * log_sigmoid(1.0)) / 2
    assert preference_loss(logits, labels, label_smoothing=0.1).item() == pytest.approx(expected)


def test_label_smoothing_bounds_the_margin_on_deterministic_labels():
    # -[0.9 log sigma(z) + 0.1 log sigma(-z)] is smallest at z = log 9; without smoothing it falls for ever.
    label = th.tensor([1.0])
    smoothed = {z: preference_loss(th.tensor([z]), label, 0.1).item() for z in (math.log(9) - 0.5, math.log(9), 8.0)}
    assert smoothed[math.log(9)] < smoothed[math.log(9) - 0.5] and smoothed[math.log(9)] < smoothed[8.0]
    assert preference_loss(th.tensor([8.0]), label).item() < preference_loss(th.tensor([math.log(9)]), label).item()


def test_a_reference_network_enters_per_step_and_carries_no_gradient():
    log_probs = LOG_PROBS.clone().requires_grad_(True)
    reference = th.tensor([[[-1.0, 0.0]], [[-2.0, -1.0]]], requires_grad=True)
    # z = 0.5 * [(-1 + 1) + (-2 - 0)] - 0.5 * [(-3 + 2) + (-1 + 1)] = -1 + 0.5 = -0.5.
    logits = dipper_logits(log_probs, FULL_MASK, 0.5, reference)
    assert logits.item() == pytest.approx(-0.5)
    logits.sum().backward()
    assert reference.grad is None and log_probs.grad is not None


def test_preference_accuracy_counts_strict_pairs_only():
    logits, labels = th.tensor([1.0, -2.0, 3.0, 0.5]), th.tensor([1.0, 1.0, 0.5, 0.0])
    # Strict pairs 0, 1, 3: logit 1 prefers tau^1 (right), -2 prefers tau^2 (wrong), 0.5 prefers tau^1 (wrong).
    assert preference_accuracy(logits, labels) == pytest.approx(1 / 3)
    assert preference_accuracy(logits, th.full((4,), 0.5)) is None


def test_tie_share_and_the_least_loss_of_a_tie():
    assert tie_share(th.tensor([1.0, 0.5, 0.0, 0.5])) == 0.5
    assert tie_share(th.tensor([1.0, 0.0])) == 0.0
    # A tie's loss -[log sigma(z) + log sigma(-z)] / 2 is smallest at z = 0, where it is ln 2: no margin to learn.
    ties = th.full((3,), 0.5)
    assert preference_loss(th.zeros(3), ties).item() == pytest.approx(math.log(2.0))
    assert preference_loss(th.tensor([-1.0, 0.3, 2.0]), ties).item() > math.log(2.0)


def test_preferred_nll_uses_the_preferred_side_and_skips_ties():
    log_probs = th.tensor([[[-1.0, -3.0], [-2.0, -2.0], [-9.0, -9.0]], [[-5.0, -5.0], [-4.0, -6.0], [-9.0, -9.0]]])
    mask = th.tensor([[[True, True], [True, True], [True, True]], [[True, True], [True, False], [True, True]]])
    labels = th.tensor([1.0, 0.0, 0.5])
    # Pair 0: tau^1 mean -2; pair 1: tau^2, one real step, -4; pair 2 (tie) is skipped. NLL = (2 + 4) / 2 = 3.
    assert preferred_nll(log_probs, mask, labels).item() == pytest.approx(3.0)
    assert preferred_nll(log_probs, mask, th.full((3,), 0.5)).item() == 0.0


def test_anchor_penalty_is_the_mean_squared_norm_of_the_offsets():
    offsets = th.tensor([[3.0, 4.0], [0.0, 1.0]], requires_grad=True)
    penalty = anchor_penalty(offsets)
    assert penalty.item() == pytest.approx((25.0 + 1.0) / 2)
    penalty.backward()  # d/do (mean_i ||o_i||^2) = 2 o / N
    assert offsets.grad.tolist() == [[3.0, 4.0], [0.0, 1.0]]


def test_real_step_values_go_back_to_their_steps_with_zero_padding():
    mask = th.tensor([[[True, False, True]], [[False, True, False]]])
    placed = at_real_steps(th.tensor([1.0, 2.0, 3.0]), mask)
    assert placed.tolist() == [[[1.0, 0.0, 2.0]], [[0.0, 3.0, 0.0]]]
    with pytest.raises(ValueError, match=r"one entry per real step of the mask \(3\)"):
        at_real_steps(th.zeros(6), mask)


def test_losses_on_real_steps_only_equal_losses_on_the_padded_batch():
    """Evaluating log-probabilities and value gaps at the real steps only (padding left at 0) changes neither the DIPPER
    loss, nor the preferred-side NLL, nor their gradients: every per-step term is masked."""
    generator = th.Generator().manual_seed(0)
    mask = th.rand(2, 5, 4, generator=generator) < 0.4
    mask[:, :, 0] = True
    labels = th.tensor([1.0, 0.0, 0.5, 1.0, 0.0])
    weights = th.randn(2, 5, 4, generator=generator)
    gaps = th.randn(2, 5, 4, generator=generator)

    def total_loss(log_probs: th.Tensor, value_gaps: th.Tensor) -> th.Tensor:
        dpo, _ = dipper_loss(log_probs, mask, labels, beta=0.1, value_gaps=value_gaps, value_reg_coef=0.1)
        return dpo + preferred_nll(log_probs, mask, labels)

    parameters = th.zeros((), requires_grad=True)
    padded = total_loss(weights * parameters.exp() - 1.0, gaps)
    (padded_gradient,) = th.autograd.grad(padded, parameters)
    real = total_loss(at_real_steps((weights * parameters.exp() - 1.0)[mask], mask), at_real_steps(gaps[mask], mask))
    (real_gradient,) = th.autograd.grad(real, parameters)
    assert real.item() == pytest.approx(padded.item(), abs=1e-6)
    assert real_gradient.item() == pytest.approx(padded_gradient.item(), abs=1e-6)
