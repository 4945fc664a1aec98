"""Pure loss functions of the preference-trained higher level (tested against hand-computed values).

Notation of the DIPPER paper (Eq. bt_log_sig_2_practical, "Eq. 9" below): a pair (tau^1, tau^2) with label ``y``
(1 when tau^1 is preferred, 0.5 for a tie), per-step log-probabilities ``log pi^H(u_t | s_t, g*)``, and per-step lower
values ``V^L(s_t, g_t)`` and ``V^L_m(s_t, g_t)`` (the lower value after m more critic steps). Tensors of per-step
terms have shape ``(2, B, T)`` with a boolean mask of the real steps.
"""

from __future__ import annotations

import math

import torch as th
import torch.nn.functional as F

# Keep atanh finite for stored actions on the boundary of [-1, 1] (float32).
ACTION_EPSILON = 1e-6


def squashed_gaussian_log_prob(mean: th.Tensor, log_std: th.Tensor, squashed_actions: th.Tensor) -> th.Tensor:
    """Log-density of stored actions ``u = tanh(x)``, ``x ~ N(mean, exp(log_std)^2)``, summed over action dims.

    ``log p(u) = log N(atanh(u); mean, std) - sum_i log(1 - u_i^2)``: the change of variables of SB3's squashed
    Gaussian, with ``u`` clipped to ``[-1 + eps, 1 - eps]`` so that boundary actions keep a finite density.
    """
    actions = squashed_actions.clamp(-1.0 + ACTION_EPSILON, 1.0 - ACTION_EPSILON)
    pre_tanh = th.atanh(actions)
    gaussian = -0.5 * ((pre_tanh - mean) / log_std.exp()) ** 2 - log_std - 0.5 * math.log(2 * math.pi)
    jacobian = th.log1p(-actions.pow(2) + ACTION_EPSILON)
    return (gaussian - jacobian).sum(dim=-1)


def uniform_log_prob(action_dim: int) -> float:
    """Log-density of the uniform reference policy on ``[-1, 1]^d`` (the "no reference policy" of max-ent DPO)."""
    return -action_dim * math.log(2.0)


def dipper_logits(
    log_probs: th.Tensor,
    mask: th.Tensor,
    beta: float,
    reference_log_prob: float | th.Tensor = 0.0,
    value_gaps: th.Tensor | None = None,
    value_reg_coef: float = 0.0,
) -> th.Tensor:
    """The logit ``z`` of Eq. 9, one per pair::

        z = sum_t beta * (log pi(u^1_t) - log pi_ref) - sum_t beta * (log pi(u^2_t) - log pi_ref)
            - lambda * sum_t [(V^L - V^L_m)(s^1_t, g^1_t) - (V^L - V^L_m)(s^2_t, g^2_t)]

    With trajectories of equal length the uniform reference cancels; it is kept so unequal lengths compare fairly.

    :param log_probs: ``(2, B, T)`` per-step log-probabilities of both trajectories
    :param mask: ``(2, B, T)`` real steps
    :param beta: the entropy (KL) weight beta
    :param reference_log_prob: per-step log-density of the reference policy: a constant (the uniform reference) or
        ``(2, B, T)`` (a reference network's, no gradient)
    :param value_gaps: ``(2, B, T)`` per-step ``V^L - V^L_m`` (no gradient), or ``None``
    :param value_reg_coef: lambda
    """
    mask = mask.to(log_probs.dtype)
    if isinstance(reference_log_prob, th.Tensor):
        reference_log_prob = reference_log_prob.detach()
    implicit_rewards = (beta * (log_probs - reference_log_prob) * mask).sum(dim=-1)
    if value_gaps is not None and value_reg_coef != 0.0:
        implicit_rewards = implicit_rewards - value_reg_coef * (value_gaps.detach() * mask).sum(dim=-1)
    return implicit_rewards[0] - implicit_rewards[1]


def at_real_steps(values: th.Tensor, mask: th.Tensor) -> th.Tensor:
    """Per-step values computed at the real steps only, put in ``mask``'s shape with 0 at the padding.

    Every per-step term of the losses here is multiplied by the mask, so evaluating the networks on the real steps
    alone gives the same losses and gradients at a fraction of the cost when trajectories are padded.

    :param values: ``(n_real,)`` values, in the row-major order of ``mask``'s true entries (``x[mask]``'s order)
    :param mask: boolean ``(2, B, T)`` real steps
    """
    n_real = int(mask.sum())
    if values.shape != (n_real,):
        raise ValueError(f"values must have one entry per real step of the mask ({n_real}), got shape {tuple(values.shape)}")
    return values.new_zeros(mask.shape).masked_scatter(mask, values)


def preference_loss(logits: th.Tensor, labels: th.Tensor, label_smoothing: float = 0.0) -> th.Tensor:
    """``-[y log sigma(z) + (1 - y) log sigma(-z)]``, averaged over pairs (Bradley-Terry with soft labels).

    :param label_smoothing: epsilon of conservative DPO: each strict label is taken as flipped with probability
        epsilon, ``y <- (1 - epsilon) y + epsilon (1 - y)`` (ties stay 0.5), so the loss is minimised at a finite
        margin ``z = log((1 - epsilon) / epsilon)`` instead of growing it without bound on deterministic labels
    """
    targets = labels.to(logits.dtype)
    if label_smoothing != 0.0:
        targets = (1.0 - label_smoothing) * targets + label_smoothing * (1.0 - targets)
    return F.binary_cross_entropy_with_logits(logits, targets)


def preference_accuracy(logits: th.Tensor, labels: th.Tensor) -> float | None:
    """Share of strict pairs (ties left out) whose logit prefers the labelled trajectory; ``None`` without strict pairs."""
    strict = labels != 0.5
    if not bool(strict.any()):
        return None
    return ((logits[strict] > 0) == (labels[strict] > 0.5)).float().mean().item()


def tie_share(labels: th.Tensor) -> float:
    """Share of ties (label 0.5) among the pairs. A tie carries no preference and its loss is at least ln 2, so a
    share near 1 leaves a preference learner nothing to learn."""
    return (labels == 0.5).float().mean().item()


def dipper_loss(
    log_probs: th.Tensor,
    mask: th.Tensor,
    labels: th.Tensor,
    beta: float,
    reference_log_prob: float | th.Tensor = 0.0,
    value_gaps: th.Tensor | None = None,
    value_reg_coef: float = 0.0,
    label_smoothing: float = 0.0,
) -> tuple[th.Tensor, th.Tensor]:
    """The DIPPER loss (Eq. 9) and its logits. ``value_reg_coef = 0`` is plain token-level DPO with a uniform reference."""
    logits = dipper_logits(log_probs, mask, beta, reference_log_prob, value_gaps, value_reg_coef)
    return preference_loss(logits, labels, label_smoothing), logits


def preferred_nll(log_probs: th.Tensor, mask: th.Tensor, labels: th.Tensor) -> th.Tensor:
    """Mean per-step negative log-likelihood of the preferred trajectory of each strict pair (ties excluded).

    Added to the DPO loss (as RPO does), it keeps the likelihood of preferred behaviour from falling while the DPO
    margin grows: the "likelihood displacement" that otherwise drives the policy toward actions seen in neither.
    """
    mask = mask.to(log_probs.dtype)
    preferred = th.where(labels > 0.5, 0, 1)
    strict = labels != 0.5
    if not bool(strict.any()):
        return log_probs.new_zeros(())
    pair_index = th.arange(labels.shape[0], device=log_probs.device)
    chosen_log_probs = log_probs[preferred, pair_index][strict]
    chosen_mask = mask[preferred, pair_index][strict]
    per_pair = (chosen_log_probs * chosen_mask).sum(dim=-1) / chosen_mask.sum(dim=-1).clamp(min=1.0)
    return -per_pair.mean()


def anchor_penalty(offsets: th.Tensor) -> th.Tensor:
    """Mean squared norm of a goal-anchored policy's offsets from the goal's action, ``mean_i ||o_i||^2``: a leash that
    keeps its subgoals at the goal unless the preference loss pulls harder.

    :param offsets: pre-``tanh`` offsets, shape ``(N, d)``
    """
    return offsets.pow(2).sum(dim=-1).mean()
