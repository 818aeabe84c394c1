"""Step baselines (cmlearn.surrogate.baselines): the constant-velocity step and least-squares linear steps."""
from __future__ import annotations

import pytest
import torch

from cmlearn.models import NodeLSTMConfig
from cmlearn.surrogate.baselines import LinearStep
from cmlearn.surrogate.evaluate import free_running, one_step

CONFIG = NodeLSTMConfig.chain((0, 1, 2, 3, 4, 5), (1, 2, 3, 4, 5), eta=2)  # anchor 0; node 5 a free end


def linear_system(nonlocal_coupling: float, V: int = 4, T: int = 120, seed: int = 0):
    """Trajectories (V, T, 6, 3) of a damped linear chain driven by random forces (V, T-1, 5, 3): each modelled
    node's second difference an affine map of its own and its neighbours' displacements over the last two frames
    and its own force, plus ``nonlocal_coupling`` times the displacement of the node two places along."""
    g = torch.Generator().manual_seed(seed)
    ref = torch.randn(6, 3, generator=g, dtype=torch.float64)
    force = 0.05 * torch.randn(V, T - 1, 5, 3, generator=g, dtype=torch.float64)
    p = ref.repeat(V, T, 1, 1)
    left, right = [0, 1, 2, 3, 4], [2, 3, 4, 5, 5]
    for t in range(1, T - 1):
        d, d1 = p[:, t] - ref, p[:, t - 1] - ref
        own = d[:, 1:]
        a = (-0.04 * own + 0.01 * (d[:, left] + d[:, right]) - 0.2 * (own - d1[:, 1:]) + 0.1 * force[:, t]
             + 0.003 + nonlocal_coupling * d[:, [3, 4, 5, 1, 2]])
        p[:, t + 1, 1:] = 2 * p[:, t, 1:] - p[:, t - 1, 1:] + a
    return p, force


def windows(p, t0: int):
    """Every history of eta + 1 = 3 frames of one trajectory ``p`` (T, 6, 3) ending at frame t0 or later."""
    return torch.stack([p[t - 2:t + 1] for t in range(t0, p.shape[0] - 1)])


def test_an_unfitted_linear_step_is_the_constant_velocity_step():
    p, f = linear_system(0.0)
    pred = one_step(LinearStep(CONFIG), p[0], f[0], 5)  # the surrogates' evaluation takes it (in float32)
    cv = 2 * p[0, 5:-1] - p[0, 4:-2]
    assert torch.allclose(pred[:, 1:].double(), cv[:, 1:], atol=1e-6) and not torch.allclose(cv, p[0, 6:], atol=1e-3)
    assert torch.equal(pred[:, 0], p[0, 6:, 0].float())  # the anchor from the data


def test_linear_steps_recover_a_linear_chain_the_local_one_only_its_local_part():
    p, f = linear_system(0.0)
    ranges = [(v, 0, p.shape[1] - 1) for v in range(3)]  # variant 3 held out
    test, ft, ref = p[3], f[3], p[3, :1].expand(p.shape[1] - 3, -1, -1)
    cv = (2 * test[2:-1] - test[1:-2] - test[3:])[:, 1:].abs().max()
    for step in (LinearStep(CONFIG).fit(p, f, ranges, ridge=0.0), LinearStep(CONFIG, local=False).fit(p, f, ranges, ridge=0.0)):
        assert (step(windows(test, 2), ft[2:], ref) - test[3:, 1:]).abs().max() < 1e-9 * cv
        # on its own predictions under the true forces (the network's rollout loop): the trajectory itself
        rolled = step.rollout(test[None, :3], ft[None, 2:], test[None, 0], anchors=test[None, 3:])[0]
        assert (rolled - test[3:]).abs().max() < 1e-8 * test.abs().max()
        assert (free_running(step, test, ft, 2).double() - test[3:]).abs().max() < 1e-4  # in float32
    # coupled to the node two places along, the chain is beyond what a node's neighbours show: the local step
    # misses that part, the global one sees every node
    p, f = linear_system(0.01)
    err = {local: float((LinearStep(CONFIG, local=local).fit(p, f, ranges, ridge=0.0)(windows(p[3], 2), f[3, 2:], ref)
                         - p[3, 3:, 1:]).abs().max()) for local in (True, False)}
    assert err[False] < 1e-9 * cv and err[True] > 1e-3 * cv
    # a ridge shrinks the weights: the fit's error grows
    assert float((LinearStep(CONFIG, local=False).fit(p, f, ranges, ridge=1e-2)(windows(p[3], 2), f[3, 2:], ref)
                  - p[3, 3:, 1:]).abs().max()) > 1e3 * err[False]


def test_linear_step_errors_name_the_parameter():
    p, f = linear_system(0.0, V=1, T=10)
    with pytest.raises(ValueError, match="ridge"):
        LinearStep(CONFIG).fit(p, f, [(0, 0, 9)], ridge=-1.0)
    with pytest.raises(ValueError, match="ranges"):
        LinearStep(CONFIG).fit(p, f, [(0, 0, 1)])
    with pytest.raises(ValueError, match="eta"):
        LinearStep(CONFIG)(p[:, :2], f[:, 0], p[:, 0])
