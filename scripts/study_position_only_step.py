"""Study (docs/surrogates.md, "A position-only step on Simulation I"): can a node step that cannot settle into a
limit cycle keep Simulation I's swing where the LSTM surrogate does not?

The step is ``p(t+1) = 2 p(t) - p(t-1) + a(p(t))``: the second difference of every modelled node is a function of
the current frame only (each node's offsets to its ``r`` tracked neighbours on either side and its displacement, as
changes from the loop's equilibrium circle, and a learned node embedding, through a tanh MLP shared by all nodes),
mirror-symmetrised (x -> -x, nodes reversed) and zero at the circle. Whatever ``a`` is, the map
``(p(t-1), p(t)) -> (p(t), p(t+1))`` is time-reversible (run from ``(p(t+1), p(t))`` it retraces its frames) and
preserves phase-space volume (its Jacobian's determinant is 1), so it has no attractor: its swing, like the undamped
LGVI's, keeps the amplitude its start gives it. What it gives up is the history: at the 10 ms step the tracked
positions alone are not the rod's state (the untracked nodes and the frames' rotations vibrate at up to several Hz).
Reversibility does not stop a force field that is not a gradient from doing work around a closed path and so pumping
energy into the swing; with ``--conservative`` the second difference is minus the gradient of a learned energy (the
network's scalar output summed over the nodes and both mirror images), so the step is Stormer-Verlet in a potential and keeps a modified
energy, as the LGVI keeps its own.

Trained with the rollout loss (squared error of every modelled node, mm) over a schedule of horizons on the task's
32 loops (the printed loop's first 60 %, loops 1-30 in full), optionally on trajectories low-passed in time
(``--lowpass`` Hz, zero phase, mirrored at both ends: at the release the motion is even in time), and
evaluated as the shipped models are: node 30's y free-running from the printed loop's 60 % cut, the held-out loop
from rest, and the fresh loops of seeds 1-3 from rest (mean over the loops of the max, and the mean error).
The last line is JSON with each stage's figures.

The best model of the study (the docs section has every run): 811 s to horizon 256, then a fine-tuning at 1024
steps from that stage's checkpoint

    python scripts/study_position_only_step.py --conservative --lowpass 1 --horizons 16:300,64:300,256:200 \
      --threads 1 --out runs/cons.pt
    python scripts/study_position_only_step.py --conservative --lowpass 1 --init runs/cons.pt --horizons 1024:150 \
      --lr 2e-4 --batch 16 --threads 2 --out runs/cons_ft.pt
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import torch
from torch import Tensor, nn

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cmlearn.data import cached_dataset  # noqa: E402
from cmlearn.data.generate import reference_rollout  # noqa: E402
from cmlearn.data.tasks import _loop_equilibrium, get_task  # noqa: E402
from cmlearn.data.windows import split_ranges  # noqa: E402
from cmlearn.io import save_torch_atomic  # noqa: E402

INTEREST = 15  # node 30 in the tracked list


class PositionOnlyStep(nn.Module):
    """The step of the module docstring for a chain of ``n`` tracked nodes whose first and last are anchors."""

    def __init__(self, rest: Tensor, r: int = 3, hidden: int = 128, depth: int = 2, embedding: int = 8,
                 d_scale: float = 0.05, p_scale: float = 0.2, a_scale: float = 1e-3, conservative: bool = False):
        super().__init__()
        self.conservative = conservative
        n = rest.shape[0]
        mod = list(range(1, n - 1))
        self.register_buffer("rest", rest.clone())
        self.register_buffer("mod", torch.tensor(mod))
        self.register_buffer("nbr", torch.tensor([[min(max(k + o, 0), n - 1) for o in range(-r, r + 1) if o]
                                                  for k in mod]))  # (K, 2 r), clamped at the anchors
        self.register_buffer("flip", torch.arange(n - 1, -1, -1))
        self.register_buffer("flip_mod", torch.tensor([n - 2 - k for k in mod]))  # slot of a node's mirror image
        self.register_buffer("mirror", torch.tensor([-1.0, 1.0, 1.0]))
        self.d_scale, self.p_scale, self.a_scale = d_scale, p_scale, a_scale
        self.emb = nn.Parameter(torch.randn(len(mod), embedding) * 0.1)
        layers, w = [], 2 * r * 3 + 3 + embedding
        for _ in range(depth):
            layers += [nn.Linear(w, hidden), nn.Tanh()]
            w = hidden
        self.net = nn.Sequential(*layers, nn.Linear(w, 1 if conservative else 3))

    def _raw(self, p: Tensor) -> Tensor:
        off = p[:, self.nbr] - p[:, self.mod, None] - (self.rest[self.nbr] - self.rest[self.mod, None])
        u = (p[:, self.mod] - self.rest[self.mod]) / self.p_scale
        return self.net(torch.cat([(off / self.d_scale).flatten(2), u, self.emb.expand(p.shape[0], -1, -1)], -1))

    def _symmetric(self, p: Tensor) -> Tensor:
        a, am = self._raw(torch.cat([p, p[:, self.flip] * self.mirror])).chunk(2)
        return 0.5 * (a + am[:, self.flip_mod] * self.mirror)

    def _force(self, p: Tensor) -> Tensor:
        if not self.conservative:
            return self._symmetric(p)
        keep = torch.is_grad_enabled()  # training: the force stays differentiable
        with torch.enable_grad():  # minus the gradient of the summed node energies of both mirror images
            x = p if p.requires_grad else p.detach().requires_grad_(True)
            energy = self._raw(torch.cat([x, x[:, self.flip] * self.mirror])).sum()
            g = torch.autograd.grad(energy, x, create_graph=keep)[0]
        return -0.5 * self.d_scale * g[:, self.mod]

    def accel(self, p: Tensor) -> Tensor:
        """The second difference (B, K, 3) in metres of frames (B, n, 3): mirror-symmetric, zero at ``rest``. With
        ``conservative`` it is minus the gradient of a learned energy (the network's output summed over the nodes
        and both mirror images) less its value at ``rest``: the force of the potential ``V(p) - grad V(rest) . p``."""
        return (self._force(p) - self._force(self.rest[None])) * self.a_scale

    def rollout(self, prev: Tensor, cur: Tensor, n: int) -> Tensor:
        """``n`` frames (B, n, n_tracked, 3) after ``prev``, ``cur`` (B, n_tracked, 3); the anchors stay put."""
        out = []
        for _ in range(n):
            nxt = cur.clone()
            nxt[:, self.mod] = 2 * cur[:, self.mod] - prev[:, self.mod] + self.accel(cur)
            prev, cur = cur, nxt
            out.append(cur)
        return torch.stack(out, 1)

    def from_rest(self, p0: Tensor, n: int) -> Tensor:
        """``n`` frames after ``p0`` (B, n_tracked, 3) released at rest: the frame before is the one after
        (``p(-h) = p(h)``), so the first step moves by half the second difference."""
        prev = p0.clone()
        prev[:, self.mod] = p0[:, self.mod] - 0.5 * self.accel(p0)
        return self.rollout(prev, p0, n)


def lowpassed(p: Tensor, hz: float, rate: float) -> Tensor:
    """Trajectories (V, T, n, 3) low-passed along time (4th-order Butterworth, zero phase, padded by mirroring at
    both ends: at the start, a release from rest, the motion is even in time); the anchors kept."""
    from scipy.signal import butter, sosfiltfilt
    sos = butter(4, hz, fs=rate, output="sos")
    out = torch.from_numpy(sosfiltfilt(sos, p.double().numpy(), axis=1, padtype="even").copy()).to(p.dtype)
    out[:, :, [0, -1]] = p[:, :, [0, -1]]
    return out


def node_errors(pred: Tensor, true: Tensor) -> tuple[float, float]:
    """Node 30's y error (mm): the mean over the batch of the max, and the mean."""
    e = (pred[..., INTEREST, 1] - true[..., INTEREST, 1]).abs() * 1e3
    return e.amax(-1).mean().item(), e.mean().item()


@torch.no_grad()
def evaluate(model: PositionOnlyStep, printed: Tensor, data_dir: str) -> dict:
    task, cut = get_task("ellipse"), int(round(0.6 * (printed.shape[0] - 1)))
    out = {"seen": node_errors(model.rollout(printed[None, cut - 1], printed[None, cut],
                                             printed.shape[0] - 1 - cut)[0], printed[cut + 1:])}
    held = reference_rollout(task, "ellipse_horizontal", data_dir=data_dir)[0].float()
    out["held_out"] = node_errors(model.from_rest(held[None, 0], held.shape[0] - 1)[0], held[1:])
    for n, seed in ((5, 1), (5, 2), (9, 3)):
        q = cached_dataset(task, n, seed, data_dir)["positions"][1:].float()
        out[f"fresh_seed{seed}"] = node_errors(model.from_rest(q[:, 0], q.shape[1] - 1), q[:, 1:])
    return out


def parse(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=20.0, help="wall-time budget of the training")
    ap.add_argument("--horizons", default="16:200,64:200,256:200,1024:100",
                    help="stages as HORIZON:ITERATIONS, each with its own cosine learning-rate schedule")
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--hidden", type=int, default=128)
    ap.add_argument("--r", type=int, default=3, help="tracked neighbours on either side each node sees")
    ap.add_argument("--noise", type=float, default=0.0, help="metres: one random shift of each start's two frames")
    ap.add_argument("--conservative", action="store_true",
                    help="the second difference is minus the gradient of a learned energy (no work around a cycle)")
    ap.add_argument("--lowpass", type=float, default=0.0, help="Hz: train on trajectories low-passed in time")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--data-dir", default="data")
    ap.add_argument("--init", default="", help="start from this run's weights (its --out file)")
    ap.add_argument("--out", default="runs/position_only_step.pt")
    a = ap.parse_args(argv)
    for name in ("minutes", "batch", "lr", "hidden", "r", "threads"):
        if getattr(a, name) <= 0:
            ap.error(f"--{name} must be positive, got {getattr(a, name)}")
    try:
        a.stages = [(int(h), int(n)) for h, n in (s.split(":") for s in a.horizons.split(","))]
    except ValueError:
        ap.error(f"--horizons must be HORIZON:ITERATIONS pairs separated by commas, got {a.horizons!r}")
    return a


def main(argv=None) -> dict:
    a = parse(argv)
    torch.manual_seed(a.seed)
    torch.set_num_threads(a.threads)
    task = get_task("ellipse")
    raw = cached_dataset(task, 32, 0, a.data_dir)["positions"]
    P = lowpassed(raw, a.lowpass, 1.0 / task.delta) if a.lowpass else raw
    V, T, n = P.shape[:3]
    train = split_ranges(V, T)["train"]  # the printed loop's first 60 %, loops 1 .. V-2 whole; the last left out
    args = {k: v for k, v in vars(a).items() if k != "stages"}
    model = PositionOnlyStep(_loop_equilibrium(task.base_scene())[list(task.tracked)].float(), r=a.r,
                             hidden=a.hidden, conservative=a.conservative)
    if a.init:
        init = torch.load(a.init, weights_only=True)
        arch = ("r", "hidden", "conservative")
        if any(init["args"].get(k, False) != getattr(a, k) for k in arch):
            raise SystemExit(f"--init {a.init}: its {arch} are {[init['args'].get(k, False) for k in arch]}")
        model.load_state_dict(init["state"])
    opt = torch.optim.Adam(model.parameters(), lr=a.lr)
    t0, stages = time.time(), []
    for H, iters in a.stages:
        ranges = [(v, first + 1, last - H) for v, first, last in train]  # start frames: one before, H after
        weight = torch.tensor([float(b - s) for _, s, b in ranges])
        for k in range(iters):
            if time.time() - t0 > a.minutes * 60:
                break
            for g in opt.param_groups:
                g["lr"] = a.lr * 0.5 * (1 + math.cos(math.pi * k / iters)) + 1e-5
            vs = torch.multinomial(weight, a.batch, replacement=True)
            ts = torch.stack([torch.randint(ranges[v][1], ranges[v][2], ()) for v in vs.tolist()])
            prev, cur = P[vs, ts - 1], P[vs, ts]
            if a.noise:
                z = torch.randn(a.batch, n, 3) * a.noise
                z[:, [0, -1]] = 0.0
                z[..., 2] = 0.0
                prev, cur = prev + z, cur + z
            true = torch.stack([P[vs, ts + j] for j in range(1, H + 1)], 1)
            loss = ((model.rollout(prev, cur, H) - true)[:, :, 1:-1] * 1e3).pow(2).mean()
            opt.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            opt.step()
            if k % 25 == 0:
                print(f"horizon {H} iteration {k}: rollout rmse {loss.sqrt().item():.3f} mm, {time.time() - t0:.0f} s",
                      file=sys.stderr, flush=True)
        save_torch_atomic(a.out, {"state": model.state_dict(), "args": args})
        ev = evaluate(model, raw[0].float(), a.data_dir)
        stages.append({"horizon": H, "wall_s": round(time.time() - t0, 1),
                       **{k: [round(x, 2) for x in v] for k, v in ev.items()}})
        print(json.dumps(stages[-1]), file=sys.stderr, flush=True)
    result = {"stages": stages, "args": args}
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
