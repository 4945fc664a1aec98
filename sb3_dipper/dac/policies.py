"""DAC's networks: SB3's SAC policy for the actor and critics, and the discriminator ``D(s, a[, g])``.

Goal envs have Dict observations, so both policy names map to SAC's ``MultiInputPolicy``. The discriminator is DAC's
(``google-research/dac/gail.py``): an MLP of two 256-unit ``tanh`` layers with orthogonal initialisation that outputs
a logit, with its own Adam optimizer (TensorFlow's default learning rate, 1e-3).
"""

from __future__ import annotations

import torch as th
from stable_baselines3.common.torch_layers import create_mlp
from stable_baselines3.sac.policies import MultiInputPolicy
from torch import nn

MlpPolicy = MultiInputPolicy


class Discriminator(nn.Module):
    """An MLP from a flat (state, action[, goal]) vector to one output per row (a logit, or a least-squares score).

    :param input_dim: size of the input vector
    :param net_arch: hidden layer sizes
    :param activation_fn: activation of the hidden layers
    :param learning_rate: learning rate of its Adam optimizer
    :param orthogonal_init: orthogonal weights and zero biases (DAC's initialisation); otherwise PyTorch's default
    """

    optimizer: th.optim.Optimizer

    def __init__(
        self,
        input_dim: int,
        net_arch: list[int],
        activation_fn: type[nn.Module],
        learning_rate: float,
        orthogonal_init: bool = True,
    ) -> None:
        super().__init__()
        self.net = nn.Sequential(*create_mlp(input_dim, 1, net_arch, activation_fn))
        if orthogonal_init:
            for layer in self.net:
                if isinstance(layer, nn.Linear):
                    nn.init.orthogonal_(layer.weight, gain=1.0)
                    nn.init.zeros_(layer.bias)
        self.optimizer = th.optim.Adam(self.parameters(), lr=learning_rate)

    def forward(self, inputs: th.Tensor) -> th.Tensor:
        """The output for each row, shape ``(N, 1)``."""
        return self.net(inputs)


__all__ = ["Discriminator", "MlpPolicy", "MultiInputPolicy"]
