"""The Rainbow-IQN-ResNet value network of Sub-controller 2 (thesis Chapter 4.1, Paper III).

``Z(x, tau) = dueling(psi(x) * phi(tau))`` returns, for each sampled quantile fraction ``tau``,
the return quantile of every action (Dabney et al. 2018, Implicit Quantile Networks):

* ``psi``: :class:`ResNetEncoder`, a residual convolutional encoder for the ``uint8 (2, 84, 84)``
  observation (scaled to [0, 1] inside). Default widths: a 4x4 stride-4 stem to 16 channels
  (21x21), one residual block (two 3x3 convolutions) at 16 channels, a stride-2 3x3 convolution to
  32 channels (11x11), one residual block at 32 channels, a stride-2 3x3 convolution (6x6x32),
  flatten and a linear layer to ``feature_dim`` = 256 features. About 5 M multiply-adds per image,
  so that training fits a 2-core CPU (the Atari IQN's Nature CNN costs about 20 M over 3 channels
  more; IMPALA's ResNet about 50 M).
* ``phi``: the cosine embedding of each fraction, ``ReLU(W [cos(pi i tau)]_{i<64} + b)``, 64
  cosine features as in the IQN paper, merged with ``psi`` by an element-wise product.
* dueling streams (Wang et al. 2016) of noisy linear layers (Fortunato et al. 2018, torchrl's
  ``NoisyLinear``, factorised Gaussian noise, ``sigma_0 = noisy_std``):
  ``Z = V + A - mean_a A``.

Noise is applied only under ``ExplorationType.RANDOM`` (torchrl's default for ``NoisyLinear``),
so evaluation under ``DETERMINISTIC`` uses the mean weights; :meth:`IQNNetwork.reset_noise`
resamples it. Acting averages ``K`` quantiles: sampled fractions under ``RANDOM``, the fixed
midpoints ``(k + 1/2) / K`` otherwise, which makes evaluation deterministic.

:func:`make_iqn_actor` wraps the network as a TorchRL ``QValueActor`` with declared keys
(``"observation"`` -> ``"action_value"``, ``"action"``, ``"chosen_action_value"``).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from torch import Tensor, nn

__all__ = ["IQNConfig", "ResNetEncoder", "ResidualBlock", "IQNNetwork", "make_iqn_actor",
           "find_iqn_network"]


@dataclass(frozen=True)
class IQNConfig:
    in_channels: int = 2
    image_size: int = 84
    num_actions: int = 4
    stem_channels: int = 16
    widths: tuple[int, ...] = (16, 32)
    feature_dim: int = 256
    hidden_dim: int = 256
    num_cosines: int = 64
    noisy_std: float = 0.5
    num_policy_quantiles: int = 32

    def __post_init__(self):
        for name in ("in_channels", "image_size", "num_actions", "stem_channels", "feature_dim", "hidden_dim",
                     "num_cosines", "num_policy_quantiles"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise ValueError(f"{name} must be an int >= 1, got {v!r}")
        if self.image_size < 16:
            raise ValueError(f"image_size must be >= 16 pixels, got {self.image_size}")
        if not self.widths or not all(isinstance(w, int) and w >= 1 for w in self.widths):
            raise ValueError(f"widths must be a non-empty tuple of ints >= 1, got {self.widths!r}")
        if not (math.isfinite(self.noisy_std) and self.noisy_std >= 0):
            raise ValueError(f"noisy_std must be finite and >= 0, got {self.noisy_std}")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["widths"] = list(self.widths)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "IQNConfig":
        d = dict(d)
        d["widths"] = tuple(d.get("widths", cls.widths))
        unknown = set(d) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown IQNConfig field(s) {sorted(unknown)}")
        return cls(**d)


class ResidualBlock(nn.Module):
    """``x + conv(relu(conv(relu(x))))`` with 3x3 convolutions (pre-activation, He et al. 2016)."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv1 = nn.Conv2d(channels, channels, 3, padding=1)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1)

    def forward(self, x: Tensor) -> Tensor:
        return x + self.conv2(torch.relu(self.conv1(torch.relu(x))))


class ResNetEncoder(nn.Module):
    """Residual encoder of ``(..., C, H, W)`` images (uint8 0-255 or float 0-1) to ``feature_dim`` features."""

    def __init__(self, config: IQNConfig):
        super().__init__()
        c = config
        layers: list[nn.Module] = [nn.Conv2d(c.in_channels, c.stem_channels, 4, stride=4)]
        prev = c.stem_channels
        for i, w in enumerate(c.widths):
            if i > 0 or w != prev:
                layers.append(nn.Conv2d(prev, w, 3, stride=2 if i > 0 else 1, padding=1))
            layers.append(ResidualBlock(w))
            prev = w
        layers += [nn.Conv2d(prev, prev, 3, stride=2, padding=1), nn.ReLU()]
        self.body = nn.Sequential(*layers)
        with torch.no_grad():
            n = self.body(torch.zeros(1, c.in_channels, c.image_size, c.image_size)).numel()
        self.fc = nn.Linear(n, c.feature_dim)
        self.in_shape = (c.in_channels, c.image_size, c.image_size)

    def forward(self, obs: Tensor) -> Tensor:
        if tuple(obs.shape[-3:]) != self.in_shape:
            raise ValueError(f"observation must have shape (..., {', '.join(map(str, self.in_shape))}), "
                             f"got {tuple(obs.shape)}")
        lead = obs.shape[:-3]
        x = obs.reshape(-1, *self.in_shape)
        x = x.float() / 255.0 if x.dtype == torch.uint8 else x.float()
        return torch.relu(self.fc(self.body(x).flatten(1))).reshape(*lead, -1)


def _noisy(i: int, o: int, std: float) -> nn.Module:
    from torchrl.modules import NoisyLinear
    return NoisyLinear(i, o, std_init=std)


class IQNNetwork(nn.Module):
    """Implicit quantile network with a ResNet encoder, cosine embedding and noisy dueling streams."""

    def __init__(self, config: IQNConfig | None = None):
        super().__init__()
        self.config = c = config or IQNConfig()
        self.encoder = ResNetEncoder(c)
        self.register_buffer("cos_index", torch.arange(c.num_cosines, dtype=torch.float32) * math.pi,
                             persistent=False)
        self.tau_embed = nn.Linear(c.num_cosines, c.feature_dim)
        self.value = nn.Sequential(_noisy(c.feature_dim, c.hidden_dim, c.noisy_std), nn.ReLU(),
                                   _noisy(c.hidden_dim, 1, c.noisy_std))
        self.advantage = nn.Sequential(_noisy(c.feature_dim, c.hidden_dim, c.noisy_std), nn.ReLU(),
                                       _noisy(c.hidden_dim, c.num_actions, c.noisy_std))

    def embed(self, taus: Tensor) -> Tensor:
        """``phi(tau)``: (..., N) fractions -> (..., N, feature_dim)."""
        return torch.relu(self.tau_embed(torch.cos(taus.unsqueeze(-1) * self.cos_index)))

    def quantiles(self, obs: Tensor, taus: Tensor, features: Tensor | None = None) -> Tensor:
        """Return quantiles ``(B, N, num_actions)`` at fractions ``taus`` (B, N) for observations (B, ...)."""
        psi = self.encoder(obs) if features is None else features
        if taus.shape[:-1] != psi.shape[:-1]:
            raise ValueError(f"taus must have shape {tuple(psi.shape[:-1])} + (N,), got {tuple(taus.shape)}")
        h = psi.unsqueeze(-2) * self.embed(taus)
        v, a = self.value(h), self.advantage(h)
        return v + a - a.mean(-1, keepdim=True)

    def policy_taus(self, batch_shape, device=None) -> Tensor:
        """The K fractions used to act: uniform samples under ``RANDOM`` exploration, fixed midpoints otherwise."""
        from torchrl.envs.utils import ExplorationType, exploration_type
        k = self.config.num_policy_quantiles
        if exploration_type() is ExplorationType.RANDOM:
            return torch.rand(*batch_shape, k, device=device)
        mid = (torch.arange(k, dtype=torch.float32, device=device) + 0.5) / k
        return mid.expand(*batch_shape, k)

    def forward(self, obs: Tensor) -> Tensor:
        """Action values ``(B, num_actions)``: the mean of K quantiles."""
        psi = self.encoder(obs)
        return self.quantiles(obs, self.policy_taus(psi.shape[:-1], psi.device), features=psi).mean(-2)

    def reset_noise(self) -> None:
        for m in self.modules():
            if m is not self and hasattr(m, "reset_noise"):
                m.reset_noise()


def make_iqn_actor(config: IQNConfig | None = None, action_space: str = "one-hot", network: IQNNetwork | None = None):
    """A TorchRL ``QValueActor`` around an :class:`IQNNetwork`: in ``"observation"``, out ``"action_value"``,
    ``"action"`` (one-hot or categorical) and ``"chosen_action_value"``."""
    from torchrl.data import Categorical, OneHot
    from torchrl.modules import QValueActor
    net = network or IQNNetwork(config)
    n = net.config.num_actions
    if action_space not in ("one-hot", "categorical"):
        raise ValueError(f"action_space must be 'one-hot' or 'categorical', got {action_space!r}")
    spec = OneHot(n) if action_space == "one-hot" else Categorical(n)
    return QValueActor(net, in_keys=["observation"], spec=spec, action_space=action_space)


def find_iqn_network(module: nn.Module) -> IQNNetwork:
    """The :class:`IQNNetwork` inside a TorchRL actor (or the network itself)."""
    for m in module.modules():
        if isinstance(m, IQNNetwork):
            return m
    raise TypeError(f"no IQNNetwork inside {type(module).__name__}")
