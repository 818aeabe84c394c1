"""The IQN loss as a TorchRL ``LossModule`` (TorchRL has none): quantile Huber regression of the
online network's return quantiles onto double-Q, n-step targets (Dabney et al. 2018).

For a sampled batch of transitions ``(s, a, R^(n), s_n, terminated)``:

* online quantiles ``Z_i = Z(s, a; tau_i)`` for ``N`` fractions ``tau_i ~ U(0, 1)``;
* double Q: the online network picks ``a* = argmax_a (1/K) sum_k Z(s_n, a; tau_k)`` (``K``
  fractions), the target network evaluates it at ``N'`` fractions:
  ``y_j = R^(n) + gamma^n (1 - terminated) Z_target(s_n, a*; tau'_j)``;
* the n-step return ``R^(n)`` and the discount ``gamma^n`` come from the data: torchrl's
  ``MultiStepTransform`` sums the discounted rewards into ``("next", "reward")`` and writes
  ``"gamma"`` (``gamma^steps``) and ``"steps_to_next_obs"``; one-step data without them uses
  ``gamma`` itself;
* loss per sample ``sum_i mean_j |tau_i - 1{y_j - Z_i < 0}| L_kappa(y_j - Z_i) / kappa`` with the
  Huber loss ``L_kappa`` (kappa = 1), weighted by the prioritized-replay importance weights
  (``"priority_weight"``) and averaged over the batch;
* the per-sample loss, detached, is written to the tensordict under ``"td_error"`` for the
  prioritized buffer's ``update_tensordict_priority``.

The target network is the loss module's ``target_value_network_params`` (created by
``convert_to_functional``), updated by torchrl's ``HardUpdate`` / ``SoftUpdate``.

Learning from demonstrations (DQfD, Hester et al. 2018): transitions marked ``expert = True`` add
the large-margin classification loss ``max_a [Q(s, a) + margin 1{a != a_E}] - Q(s, a_E)`` (``Q`` the
mean of the N online quantiles), times ``margin_weight`` and averaged over the batch, so that the
demonstrated action's value stays above the others by ``margin``; without the key, or with
``margin_weight = 0``, the loss is plain IQN.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictParams
from torch import Tensor
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives import LossModule

from cmlearn.models.iqn import IQNNetwork, find_iqn_network

__all__ = ["quantile_huber_loss", "IQNLoss"]


def quantile_huber_loss(pred: Tensor, target: Tensor, taus: Tensor, kappa: float = 1.0) -> Tensor:
    """Per-sample quantile Huber loss: ``pred`` (B, N) at fractions ``taus`` (B, N) against ``target`` (B, N').

    Returns (B,): the sum over the N predicted quantiles of the mean over the N' target samples."""
    if not (math.isfinite(kappa) and kappa > 0):
        raise ValueError(f"kappa must be finite and > 0, got {kappa}")
    if pred.shape != taus.shape or pred.ndim != 2 or target.ndim != 2 or pred.shape[0] != target.shape[0]:
        raise ValueError(f"pred and taus must both be (B, N) and target (B, N'), got pred {tuple(pred.shape)}, "
                         f"taus {tuple(taus.shape)}, target {tuple(target.shape)}")
    delta = target.unsqueeze(-2) - pred.unsqueeze(-1)                 # (B, N, N'): y_j - Z_i
    ad = delta.abs()
    huber = torch.where(ad <= kappa, 0.5 * delta ** 2, kappa * (ad - 0.5 * kappa))
    weight = (taus.unsqueeze(-1) - (delta.detach() < 0).to(pred.dtype)).abs()
    return (weight * huber / kappa).mean(-1).sum(-1)


@dataclass
class _Keys:
    action: str = "action"
    observation: str = "observation"
    reward: str = "reward"
    terminated: str = "terminated"
    priority: str = "td_error"
    priority_weight: str = "priority_weight"
    gamma: str = "gamma"
    expert: str = "expert"


class IQNLoss(LossModule):
    """Quantile Huber loss with double-Q n-step targets for an :class:`~cmlearn.models.iqn.IQNNetwork` actor.

    Args:
        value_network: a TorchRL actor containing an ``IQNNetwork`` (see ``make_iqn_actor``).
        gamma: one-step discount; the data's ``"gamma"`` entry (``gamma^n`` from ``MultiStepTransform``)
            takes precedence.
        num_quantiles, num_target_quantiles: N and N' (64 in the IQN paper; 32 here by default).
        num_policy_quantiles: K for the double-Q argmax (default: the network's).
        kappa: the Huber threshold (1).
        noisy: evaluate the networks with their noise on (``ExplorationType.RANDOM``), as in Rainbow.
        margin, margin_weight: the DQfD large-margin loss on ``expert`` transitions (0.8 and 1 in DQfD).
    """

    default_keys = _Keys
    value_network: TensorDictModule
    value_network_params: TensorDictParams
    target_value_network_params: TensorDictParams

    def __init__(self, value_network: TensorDictModule, *, gamma: float = 0.99, num_quantiles: int = 32,
                 num_target_quantiles: int = 32, num_policy_quantiles: int | None = None, kappa: float = 1.0,
                 noisy: bool = True, margin: float = 0.8, margin_weight: float = 1.0):
        super().__init__()
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {gamma}")
        for name, v in (("num_quantiles", num_quantiles), ("num_target_quantiles", num_target_quantiles)):
            if not (isinstance(v, int) and v >= 1):
                raise ValueError(f"{name} must be an int >= 1, got {v!r}")
        k = num_policy_quantiles
        if k is not None and not (isinstance(k, int) and k >= 1):
            raise ValueError(f"num_policy_quantiles must be None or an int >= 1, got {num_policy_quantiles!r}")
        if not (math.isfinite(kappa) and kappa > 0):
            raise ValueError(f"kappa must be finite and > 0, got {kappa}")
        for name, v in (("margin", margin), ("margin_weight", margin_weight)):
            if not (v >= 0 and v < float("inf")):
                raise ValueError(f"{name} must be finite and >= 0, got {v}")
        find_iqn_network(value_network)  # fail early on a network without an IQN head
        self.convert_to_functional(value_network, "value_network", create_target_params=True)
        self.gamma, self.kappa, self.noisy = float(gamma), float(kappa), noisy
        self.num_quantiles, self.num_target_quantiles = num_quantiles, num_target_quantiles
        self.num_policy_quantiles = num_policy_quantiles
        self.margin, self.margin_weight = float(margin), float(margin_weight)
        self.keys = _Keys()

    @property
    def net(self) -> IQNNetwork:
        return find_iqn_network(self.value_network)

    @property
    def in_keys(self):
        k = self.keys
        return [k.action, k.observation, ("next", k.observation), ("next", k.reward), ("next", k.terminated)]

    def _mode(self):
        return set_exploration_type(ExplorationType.RANDOM if self.noisy else ExplorationType.DETERMINISTIC)

    def reset_noise(self) -> None:
        """Resample the factorised noise of the online and the target network, independently.

        Written straight into both parameter sets (the online set shares storage with the actor
        the collector runs), so no module state is swapped."""
        from torchrl.modules import NoisyLinear

        def scaled(n: int, like: Tensor) -> Tensor:
            x = torch.randn(n, dtype=like.dtype, device=like.device)
            return x.sign() * x.abs().sqrt()

        for name, m in self.value_network.named_modules():
            if not isinstance(m, NoisyLinear):
                continue
            key = tuple(name.split("."))
            for params in (self.value_network_params, self.target_value_network_params):
                w = params.get(key + ("weight_epsilon",))
                e_out, e_in = scaled(m.out_features, w), scaled(m.in_features, w)
                w.data.copy_(torch.outer(e_out, e_in))
                b = params.get(key + ("bias_epsilon",), None)
                if b is not None:
                    b.data.copy_(e_out)

    def _action_index(self, action: Tensor) -> Tensor:
        n = self.net.config.num_actions
        if action.shape[-1:] == (n,) and action.dtype in (torch.int64, torch.bool, torch.int32, torch.uint8) \
                and action.ndim >= 2:
            return action.long().argmax(-1)
        return action.reshape(action.shape[0]).long()

    def _discount(self, td: TensorDictBase, batch: int, ref: Tensor) -> Tensor:
        g = td.get(self.keys.gamma, None)
        if g is None:
            return torch.full((batch,), self.gamma, dtype=ref.dtype, device=ref.device)
        return g.reshape(batch).to(ref.dtype)

    @torch.no_grad()
    def target_quantiles(self, td: TensorDictBase) -> tuple[Tensor, Tensor]:
        """``(a*, y)``: the online network's greedy next action (B,) and the target quantiles (B, N')."""
        obs_next = td.get(("next", self.keys.observation))
        B = obs_next.shape[0]
        net = self.net
        k = self.num_policy_quantiles or net.config.num_policy_quantiles
        with self._mode():
            with self.value_network_params.data.to_module(self.value_network):
                q_next = net.quantiles(obs_next, torch.rand(B, k, device=obs_next.device)).mean(-2)
            a_star = q_next.argmax(-1)
            with self.target_value_network_params.data.to_module(self.value_network):
                z = net.quantiles(obs_next, torch.rand(B, self.num_target_quantiles, device=obs_next.device))
        z = z.gather(-1, a_star.view(B, 1, 1).expand(B, z.shape[1], 1)).squeeze(-1)
        r = td.get(("next", self.keys.reward)).reshape(B).to(z.dtype)
        term = td.get(("next", self.keys.terminated)).reshape(B).to(z.dtype)
        y = r.unsqueeze(-1) + (self._discount(td, B, z) * (1.0 - term)).unsqueeze(-1) * z
        return a_star, y

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        obs = tensordict.get(self.keys.observation)
        B = obs.shape[0]
        if tensordict.ndim != 1:
            raise ValueError(f"IQNLoss expects a flat batch of transitions, got batch_size {tensordict.batch_size}")
        k = self.keys
        for key in (k.observation, ("next", k.observation), ("next", k.reward), k.gamma, k.priority_weight):
            v = tensordict.get(key, None)  # a NaN here would silently turn the weights and priorities into NaN
            if v is not None and v.is_floating_point() and not torch.isfinite(v).all():
                raise ValueError(f"IQNLoss: the batch's {key!r} has non-finite values")
        action = self._action_index(tensordict.get(self.keys.action))
        _, y = self.target_quantiles(tensordict)
        taus = torch.rand(B, self.num_quantiles, device=obs.device)
        with self._mode(), self.value_network_params.to_module(self.value_network):
            z_all = self.net.quantiles(obs, taus)                          # (B, N, A)
        z = z_all.gather(-1, action.view(B, 1, 1).expand(B, z_all.shape[1], 1)).squeeze(-1)
        per_sample = quantile_huber_loss(z, y, taus, self.kappa)
        tensordict.set(self.keys.priority, per_sample.detach().to(tensordict.device or per_sample.device))
        w = tensordict.get(self.keys.priority_weight, None)
        loss = (per_sample * w.reshape(B).to(per_sample.dtype)).mean() if w is not None else per_sample.mean()
        out = {"q_mean": z.detach().mean(), "td_error_mean": per_sample.detach().mean()}
        expert = tensordict.get(self.keys.expert, None)
        if expert is not None and self.margin_weight > 0:
            margin = self.margin_loss(z_all.mean(-2), action) * expert.reshape(B).to(z.dtype)
            loss = loss + self.margin_weight * margin.mean()
            out["margin_loss"] = margin.detach().sum() / expert.sum().clamp(min=1)
        out["loss"] = loss
        return TensorDict(out)

    def margin_loss(self, q: Tensor, expert_action: Tensor) -> Tensor:
        """Per-sample ``max_a [q_a + margin 1{a != a_E}] - q_{a_E}`` for values ``q`` (B, A)."""
        l = torch.full_like(q, self.margin).scatter(-1, expert_action.view(-1, 1), 0.0)
        return (q + l).max(-1).values - q.gather(-1, expert_action.view(-1, 1)).squeeze(-1)
