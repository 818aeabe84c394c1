"""Linearised discrete rod: stiffness (Hessian of the elastic energy at the straight
configuration), lumped mass/inertia, natural frequencies and the fastest mode.

Used for the frequency correction gamma_corr and the stable time step of the explicit LGVI
update (Stormer-Verlet is stable for ``h omega_max < 2``). The stiffness is assembled from
per-element 12x12 Hessians computed with ``torch.func``.
"""
from __future__ import annotations

import functools

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg
import torch

from .checks import is_int
from .elastic import elastic_energy
from .lie import so3_exp

__all__ = ["stiffness_and_mass", "frequencies", "max_frequency"]

_DENSE_MAX = 1500


def _element_hessians(rod, energy_fn=elastic_energy):
    prm = rod.params(torch.float64)
    N = rod.N

    def energy(x, l, C1, C2, k0):
        pa, pb = x[0:3], x[6:9] + torch.stack((torch.zeros_like(l), torch.zeros_like(l), l))
        Ra, Rb = so3_exp(x[3:6]), so3_exp(x[9:12])
        sub = prm._replace(l=l[None], C1=C1[None], C2=C2[None], kappa0=k0[None])
        return energy_fn(torch.stack((pa, pb)), torch.stack((Ra, Rb)), sub)

    x0 = torch.zeros(N, 12, dtype=torch.float64)
    H = torch.func.vmap(torch.func.hessian(energy))(x0, prm.l, prm.C1, prm.C2, prm.kappa0)
    return H.numpy(), prm


def stiffness_and_mass(rod, energy_fn=elastic_energy):
    """Sparse stiffness K (6n x 6n, DOFs [dp, dtheta] per node) and the diagonal mass vector.
    ``energy_fn(p, R, params)`` is the discrete elastic energy (default: the LGVI's)."""
    H, prm = _element_hessians(rod, energy_fn)
    n, N = rod.n_nodes, rod.N
    rows, cols, vals = [], [], []
    idx = np.arange(12)
    for e in range(N):
        g = 6 * e + idx
        rows.append(np.repeat(g, 12))
        cols.append(np.tile(g, 12))
        vals.append(H[e].ravel())
    K = scipy.sparse.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                                shape=(6 * n, 6 * n)).tocsr()
    m = prm.mass.numpy()
    J = prm.inertia.numpy()
    mass = np.concatenate([np.concatenate((np.full(3, m[a]), J[a])) for a in range(n)])
    return K, mass


def _reduced(rod, bc: str, energy_fn=elastic_energy):
    K, mass = stiffness_and_mass(rod, energy_fn)
    n = rod.n_nodes
    fixed = {"clamped-free": [0], "prescribed-base": [0], "clamped-clamped": [0, n - 1], "free-free": []}
    if bc not in fixed:
        raise ValueError(f"bc must be one of {sorted(fixed)}, got {bc!r}")
    keep = np.array([i for i in range(6 * n) if i // 6 not in fixed[bc]])
    K = K[keep][:, keep]
    s = 1.0 / np.sqrt(mass[keep])
    A = scipy.sparse.diags(s) @ K @ scipy.sparse.diags(s)
    return A


def frequencies(rod, bc: str = "clamped-free", n_modes: int = 6, energy_fn=elastic_energy) -> torch.Tensor:
    """Lowest ``n_modes`` non-rigid angular frequencies (rad/s), float64, of the rod linearised about the straight
    configuration: an error for a rod with intrinsic curvature, whose straight configuration is no equilibrium."""
    if any(k != 0 for k in getattr(rod, "intrinsic_curvature", (0.0, 0.0, 0.0))):
        raise ValueError("frequencies: the modes are those about the straight rod, and a rod with "
                         f"intrinsic_curvature {tuple(rod.intrinsic_curvature)} is not at rest straight")
    if not (is_int(n_modes) and n_modes >= 1):  # numpy ints too
        raise ValueError(f"frequencies: n_modes must be an integer >= 1, got {n_modes!r}")
    A = _reduced(rod, bc, energy_fn)
    n_rigid = 6 if bc == "free-free" else 0
    if n_modes + n_rigid > A.shape[0]:  # eigh would return fewer modes than asked for
        raise ValueError(f"frequencies: n_modes={n_modes} exceeds the {A.shape[0] - n_rigid} non-rigid modes of "
                         f"this {rod.N}-element rod ({bc})")
    k = int(n_modes) + n_rigid
    if A.shape[0] <= _DENSE_MAX or k >= A.shape[0]:  # eigsh needs k below the size
        lam = scipy.linalg.eigh(A.toarray(), eigvals_only=True, subset_by_index=[0, k - 1])
    else:
        # shift-invert just below 0, scaled to A: a fixed shift is lost in round-off beside stiff entries and
        # leaves the free-free (singular) A singular or lets rigid modes pass for elastic ones
        sigma = -1e-10 * float(abs(A.diagonal()).max())
        lam = np.sort(scipy.sparse.linalg.eigsh(A.tocsc(), k=k, sigma=sigma, which="LM",
                                                return_eigenvectors=False))
    lam = lam[n_rigid:]
    return torch.tensor(np.sqrt(np.clip(lam, 0.0, None)), dtype=torch.float64)


@functools.lru_cache(maxsize=64)
def max_frequency(rod) -> float:
    """Fastest angular frequency of the free-free linearised model (rad/s)."""
    A = _reduced(rod, "free-free")
    if A.shape[0] <= _DENSE_MAX:  # a full symmetric eigensolve is faster here than a subset one
        lam = scipy.linalg.eigvalsh(A.toarray())[-1]
    else:
        lam = scipy.sparse.linalg.eigsh(A, k=1, which="LA", return_eigenvectors=False)[0]
    return float(np.sqrt(lam))
