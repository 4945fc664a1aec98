"""PIPER's networks: the higher SAC's policy (HIER's) and the reward model ``r_phi(s, g, u)`` it is trained on."""

from __future__ import annotations

from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BaseModel
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, CombinedExtractor, create_mlp
from stable_baselines3.common.type_aliases import PyTorchObs
from torch import nn

from sb3_dipper.hier.policies import MlpPolicy, MultiInputPolicy


class RewardModel(BaseModel):
    """PIPER's reward model over higher-level transitions: ``r_phi(s, g, u) = tanh(MLP([s, g, u]))``.

    As in the authors' code (``actor_critic_sac.py``): the observation (state and goal: every key of the goal env's
    Dict, flattened and concatenated) and the higher-level action ``u`` in ``[-1, 1]^d``, an MLP, and a ``tanh``
    output, so that a trajectory's return stays within ``(-T, T)``.

    :param observation_space: the goal env's Dict observation space
    :param action_space: the higher-level action space ``[-1, 1]^d``
    :param learning_rate: learning rate of its optimizer
    :param net_arch: hidden layer sizes
    :param activation_fn: activation function
    :param features_extractor_class: features extractor (default: SB3's ``CombinedExtractor``)
    :param features_extractor_kwargs: its keyword arguments
    :param normalize_images: whether to divide image observations by 255
    :param optimizer_class: optimizer class
    :param optimizer_kwargs: optimizer keyword arguments (besides the learning rate)
    """

    features_extractor: BaseFeaturesExtractor

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        learning_rate: float = 1e-3,
        net_arch: list[int] | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        features_extractor_class: type[BaseFeaturesExtractor] = CombinedExtractor,
        features_extractor_kwargs: dict[str, Any] | None = None,
        normalize_images: bool = True,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
    ) -> None:
        super().__init__(
            observation_space,
            action_space,
            features_extractor_class,
            features_extractor_kwargs,
            normalize_images=normalize_images,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
        )
        self.net_arch = [256, 256] if net_arch is None else net_arch
        self.activation_fn = activation_fn
        self.features_extractor = self.make_features_extractor()
        input_dim = self.features_extractor.features_dim + get_action_dim(action_space)
        self.reward_net = nn.Sequential(*create_mlp(input_dim, 1, self.net_arch, activation_fn, squash_output=True))
        self.optimizer = self.optimizer_class(self.parameters(), lr=learning_rate, **self.optimizer_kwargs)  # type: ignore[call-arg]

    def forward(self, obs: PyTorchObs, actions: th.Tensor) -> th.Tensor:
        """``r_phi(s, g, u)`` of a batch of observations and higher-level actions, shape ``(N,)``."""
        features = self.extract_features(obs, self.features_extractor)
        return self.reward_net(th.cat([features, actions], dim=1)).squeeze(-1)


__all__ = ["MlpPolicy", "MultiInputPolicy", "RewardModel"]
