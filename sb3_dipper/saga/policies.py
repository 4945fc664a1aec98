"""SAGA's networks: the higher SAC's policy (HIER's) and the subgoal discriminator ``D(s, g)``."""

from __future__ import annotations

from itertools import pairwise
from typing import Any

import torch as th
from torch import nn

from sb3_dipper.hier.policies import MlpPolicy, MultiInputPolicy


class SubgoalDiscriminator(nn.Module):
    """SAGA's discriminator: the logit that subgoal ``g`` was reached from state ``s`` rather than generated there.

    An MLP over ``[s, g]`` (``state_dim = 0``: over ``g`` alone, as the released code's ``Discriminator``), with the
    released code's sizes ``[64, 16]`` and ``LeakyReLU(0.2)``. It returns a logit: the released code's final sigmoid is
    folded into the losses (:func:`sb3_dipper.saga.saga.discriminator_loss`), which is the same model, computed stably.

    :param state_dim: size of the state part of the input (0: a subgoal-only discriminator ``D(g)``)
    :param subgoal_dim: size of a subgoal (in the higher level's ``[-1, 1]^d`` coordinates)
    :param learning_rate: learning rate of its optimizer (released code: 2e-4)
    :param net_arch: hidden layer sizes
    :param negative_slope: negative slope of the ``LeakyReLU`` activations
    :param optimizer_class: optimizer class
    :param optimizer_kwargs: optimizer keyword arguments (besides the learning rate)
    """

    def __init__(
        self,
        state_dim: int,
        subgoal_dim: int,
        learning_rate: float = 2e-4,
        net_arch: list[int] | None = None,
        negative_slope: float = 0.2,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
    ) -> None:
        super().__init__()
        self.state_dim = state_dim
        self.net_arch = [64, 16] if net_arch is None else net_arch
        sizes = [state_dim + subgoal_dim, *self.net_arch]
        layers: list[nn.Module] = []
        for n_in, n_out in pairwise(sizes):
            layers += [nn.Linear(n_in, n_out), nn.LeakyReLU(negative_slope)]
        self.net = nn.Sequential(*layers, nn.Linear(sizes[-1], 1))
        self.optimizer = optimizer_class(self.parameters(), lr=learning_rate, **(optimizer_kwargs or {}))  # type: ignore[call-arg]

    def forward(self, states: th.Tensor | None, subgoals: th.Tensor) -> th.Tensor:
        """Logits ``D(s, g)``, shape ``(N,)``; ``states`` is ``None`` for a subgoal-only discriminator."""
        if self.state_dim == 0:
            return self.net(subgoals).squeeze(-1)
        assert states is not None, "a state-conditioned discriminator needs the states"
        return self.net(th.cat([states, subgoals], dim=1)).squeeze(-1)


__all__ = ["MlpPolicy", "MultiInputPolicy", "SubgoalDiscriminator"]
