"""Ergodic control: spectral multiscale coverage (SMC) and heat-equation driven area coverage (HEDAC)
(seed 004 §10).

Shapes and conventions, shared by every function here:

* The domain is the box ``[0, ℓ]^D`` (``length = ℓ``).  The Fourier series of §10.1 uses the period
  ``L = 2ℓ``: the distribution on ``[0, ℓ]^D`` is mirrored along every axis to an even, ``L``-periodic
  signal (Fig. 42-(d)), so only cosines are needed (Table 1, symmetry property).
* ``n_basis = K`` functions per dimension; the index set ``𝒦 = {0..K-1}^D`` (§10.1.2) is ordered
  row-major (last dimension fastest, :func:`fourier_indices`), giving ``K^D`` basis functions.
* Agent positions are ``x (*B, N, D)`` (``N`` agents, ``N = 1`` for one agent), trajectories
  ``(*B, T, N, D)`` (time before agents); any number of leading batch dims, broadcasting like torch.
  Several agents share one set of time-averaged coefficients ``w`` (multi-agent SMC).
* Coefficient vectors are ``(*B, K^D)``.  Nothing is cast: dtype and device follow the inputs.

SMC (§10.1): basis ``φ_k(x) = L^{-D} ∏_d cos(2π k_d x_d / L)`` (Eq. 123, 150-152) and its gradient
(Eq. 124, 153-156); coefficients of a Gaussian mixture (Table 1: Gaussian, shift and combination
properties, Eq. 126/144); weights ``Λ_k = (1 + ‖k‖²)^{-(D+1)/2}`` (Eq. 130, 149); metric
``ε = ½ Σ_k Λ_k (w_k − ŵ_k)²`` (Eq. 129, 147) with ``w`` the time average of ``φ`` along the trajectory
(Eq. 127, 145); the myopic controller ``u = u_max ũ/‖ũ‖``, ``ũ = −∇φ(x)ᵀ Λ (w − ŵ)`` (Eq. 138, 159) on the
velocity-controlled agent ``ẋ = u``; and the planning form (Eq. 139-142, :func:`smc_plan`): Gauss-Newton on
the whole command sequence, started from the myopic rollout.

HEDAC (§10.2): on a cell-centred grid of ``G`` cells per dimension (:class:`HeatGrid`), the residual
``e = p − c`` (Eq. 160), source ``s = max(e, 0)² / ∫ max(e, 0)²`` (Eq. 161-162), explicit heat equation
``∂u/∂t = α Δu + s`` with insulated (Neumann) walls (Eq. 163, 165), agents moved along ``∇u`` (Eq. 164)
at speed ``u_max``, coverage ``c`` = normalized sum of the agents' Gaussian footprints ``exp(−(ε‖x−x_i‖)²)``
along their paths (Eq. 166-168).  Fields are ``(*B, G, ..., G)`` (``D`` trailing grid dims).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import NamedTuple

import torch

from torchlie._batch import check_same_device

__all__ = [
    "fourier_indices",
    "fourier_basis",
    "fourier_basis_grad",
    "sobolev_weights",
    "gmm_fourier_coefficients",
    "gmm_density",
    "running_coefficients",
    "ergodic_metric",
    "SMCState",
    "SMCStep",
    "SMCRollout",
    "smc_init",
    "smc_control",
    "smc_step",
    "smc_rollout",
    "SMCPlan",
    "smc_plan",
    "HeatGrid",
    "HEDACState",
    "HEDACStep",
    "HEDACRollout",
    "heat_step",
    "hedac_source",
    "agent_footprint",
    "field_gradient_at",
    "hedac_init",
    "hedac_step",
    "hedac_rollout",
]


# ----------------------------------------------------------------------------------------------------------
# argument checks (private)

def _tensor(x, name: str, fn: str, min_dim: int = 1) -> torch.Tensor:
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{fn}: argument '{name}' must be a torch.Tensor, got {type(x).__name__}")
    if not x.dtype.is_floating_point:
        raise TypeError(f"{fn}: argument '{name}' must have a floating dtype, got {x.dtype}")
    if x.dim() < min_dim:
        raise ValueError(f"{fn}: argument '{name}' must have at least {min_dim} dims, got shape "
                         f"{tuple(x.shape)}")
    return x


def _agents(x: torch.Tensor, name: str, fn: str) -> torch.Tensor:
    """``x (*B, N, D)`` with at least one agent (an average over ``N = 0`` agents would be NaN)."""
    if x.shape[-2] < 1:
        raise ValueError(f"{fn}: argument '{name}' must hold N >= 1 agents (dim -2 of (..., N, D)), got "
                         f"{tuple(x.shape)}")
    return x


def _pos_int(v, name: str, fn: str, minimum: int = 1) -> int:
    if not isinstance(v, numbers.Integral) or isinstance(v, bool) or v < minimum:
        raise ValueError(f"{fn}: argument '{name}' must be an int >= {minimum}, got {v!r}")
    return int(v)


def _pos_float(v, name: str, fn: str, allow_zero: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(float(v)) or (
            float(v) < 0 if allow_zero else float(v) <= 0):
        what = "a finite float >= 0" if allow_zero else "a finite float > 0"
        raise ValueError(f"{fn}: argument '{name}' must be {what}, got {v!r}")
    return float(v)


def _check_coeffs(w: torch.Tensor, name: str, fn: str, n_coef: int) -> None:
    if w.shape[-1] != n_coef:
        raise ValueError(f"{fn}: argument '{name}' must be (*B, K^D) = (*B, {n_coef}), got "
                         f"{tuple(w.shape)}")


def _safe_normalize(v: torch.Tensor, scale: float) -> torch.Tensor:
    """``scale · v / ‖v‖`` over the last dim, ``0`` where ``v = 0`` (finite gradients there too)."""
    n2 = (v * v).sum(-1, keepdim=True)
    zero = n2 == 0                                                     # NaN stays NaN
    safe = torch.where(zero, torch.ones_like(n2), n2)
    return torch.where(zero, torch.zeros_like(v), v * (scale / safe.sqrt()))


# ----------------------------------------------------------------------------------------------------------
# SMC: Fourier basis, coefficients, metric (§10.1)

def fourier_indices(n_dims: int, n_basis: int, *, device: torch.device | str | None = None) -> torch.Tensor:
    """The index vectors ``k ∈ 𝒦 = {0, ..., K-1}^D`` (§10.1.2) as a ``(K^D, D)`` long tensor (``Ṽᵀ`` of
    Eq. 152), row-major: the last dimension varies fastest (``D=2, K=2``: ``[0,0], [0,1], [1,0], [1,1]``)."""
    D = _pos_int(n_dims, "n_dims", "fourier_indices")
    K = _pos_int(n_basis, "n_basis", "fourier_indices")
    r = torch.arange(K, device=device)
    grids = torch.meshgrid(*([r] * D), indexing="ij")
    return torch.stack([g.reshape(-1) for g in grids], dim=-1)


def _frequencies(n_dims: int, n_basis: int, length: float, x: torch.Tensor) -> torch.Tensor:
    """``V = 2π Ṽ / L`` as ``(K^D, D)``, with the period ``L = 2ℓ`` (Eq. 137, 152)."""
    k = fourier_indices(n_dims, n_basis, device=x.device).to(x.dtype)
    return k * (math.pi / length)


def _basis_args(x, n_basis, length, fn: str) -> tuple[torch.Tensor, int, int, float]:
    x = _tensor(x, "x", fn)
    K = _pos_int(n_basis, "n_basis", fn)
    ell = _pos_float(length, "length", fn)
    return x, x.shape[-1], K, ell


def fourier_basis(x: torch.Tensor, *, n_basis: int, length: float) -> torch.Tensor:
    """Cosine basis ``φ(x) = L^{-D} ⊙_d cos(V_d x_d)``, ``L = 2ℓ`` (Eq. 123/136 for ``D = 1``, Eq. 150-152).

    Args:
        x: points ``(*B, D)`` in the domain ``[0, ℓ]^D``.
        n_basis: ``K``, functions per dimension.
        length: ``ℓ``, the side of the domain.

    Returns:
        ``(*B, K^D)``, ordered as :func:`fourier_indices`.
    """
    x, D, K, ell = _basis_args(x, n_basis, length, "fourier_basis")
    V = _frequencies(D, K, ell, x)
    return torch.cos(x[..., None, :] * V).prod(-1) / (2.0 * ell) ** D


def fourier_basis_grad(x: torch.Tensor, *, n_basis: int, length: float) -> torch.Tensor:
    """Gradient of :func:`fourier_basis`, ``∇_x φ(x)`` (Eq. 124/137 for ``D = 1``, Eq. 153-156).

    Column ``d`` is ``−L^{-D} V_d ⊙ sin(V_d x_d) ⊙_{i≠d} cos(V_i x_i)``.

    Args:
        x: ``(*B, D)``.

    Returns:
        ``(*B, K^D, D)``: row ``k`` is ``∂φ_k/∂x``.
    """
    x, D, K, ell = _basis_args(x, n_basis, length, "fourier_basis_grad")
    V = _frequencies(D, K, ell, x)
    a = x[..., None, :] * V                                            # (*B, K^D, D)
    c, ds = torch.cos(a), -V * torch.sin(a)
    eye = torch.eye(D, dtype=torch.bool, device=x.device)              # [d_out, d_in]
    terms = torch.where(eye, ds[..., None, :], c[..., None, :])        # (*B, K^D, D_out, D_in)
    return terms.prod(-1) / (2.0 * ell) ** D


def sobolev_weights(n_dims: int, n_basis: int, *, dtype: torch.dtype = torch.float64,
                    device: torch.device | str | None = None) -> torch.Tensor:
    """``Λ_k = (1 + ‖k‖²)^{-(D+1)/2}`` (Eq. 130 for ``D = 1``, Eq. 149), ``(K^D,)``."""
    k = fourier_indices(n_dims, n_basis, device=device).to(dtype)
    return (1.0 + (k * k).sum(-1)) ** (-(n_dims + 1) / 2.0)


def _check_gmm(weights, means, covariances, fn: str) -> int:
    means = _tensor(means, "means", fn, 2)
    weights = _tensor(weights, "weights", fn, 1)
    covariances = _tensor(covariances, "covariances", fn, 3)
    D = means.shape[-1]
    J = means.shape[-2]
    if covariances.shape[-3:] != (J, D, D):
        raise ValueError(f"{fn}: argument 'covariances' must be (*B, J, D, D) = (*B, {J}, {D}, {D}) to match "
                         f"'means' {tuple(means.shape)}, got {tuple(covariances.shape)}")
    if weights.shape[-1] != J:
        raise ValueError(f"{fn}: argument 'weights' must be (*B, J) with J = {J} (from 'means'), got "
                         f"{tuple(weights.shape)}")
    check_same_device(fn, means=means, weights=weights, covariances=covariances)
    return D


def gmm_fourier_coefficients(weights: torch.Tensor, means: torch.Tensor, covariances: torch.Tensor, *,
                             n_basis: int, length: float) -> torch.Tensor:
    """Fourier coefficients ``ŵ_k = ∫ ĝ(x) φ_k(x) dx`` of a Gaussian mixture ``ĝ = Σ_j α_j 𝒩(μ_j, Σ_j)``
    (Eq. 126/144), in closed form from the properties of Table 1.

    Mirroring ``ĝ`` along every axis (Fig. 42-(d)) gives the even signal whose cosine coefficients are,
    by the Gaussian, shift and combination properties,
    ``ŵ_k = L^{-D} Σ_j α_j 2^{-D} Σ_{s∈{±1}^D} cos(ω_sᵀ μ_j) exp(−½ ω_sᵀ Σ_j ω_s)``, ``ω_s = s ⊙ V_k``.
    This is exact for the integral over ``ℝ^D``, which equals the integral over ``[0, ℓ]^D`` of the
    mixture folded back into the domain by reflection at its walls; for components well inside the
    domain it is the integral (Eq. 144) itself.  Differentiable in all arguments.

    Args:
        weights: ``α (*B, J)`` (summing to 1 for a probability density; not enforced).
        means: ``μ (*B, J, D)``.
        covariances: ``Σ (*B, J, D, D)``, symmetric positive semidefinite.

    Returns:
        ``ŵ (*B, K^D)``.
    """
    fn = "gmm_fourier_coefficients"
    D = _check_gmm(weights, means, covariances, fn)
    K = _pos_int(n_basis, "n_basis", fn)
    ell = _pos_float(length, "length", fn)
    V = _frequencies(D, K, ell, means)                                 # (K^D, D)
    signs = torch.tensor([[1.0 - 2.0 * ((i >> d) & 1) for d in range(D)] for i in range(2 ** D)],
                         dtype=means.dtype, device=means.device)       # (S, D)
    omega = signs[:, None, :] * V                                      # (S, K^D, D)
    phase = torch.einsum("skd,...jd->...jsk", omega, means)
    quad = torch.einsum("skd,...jde,ske->...jsk", omega, covariances, omega)
    per_comp = (torch.cos(phase) * torch.exp(-0.5 * quad)).mean(-2)    # (*B, J, K^D)
    return (weights[..., None] * per_comp).sum(-2) / (2.0 * ell) ** D


def gmm_density(x: torch.Tensor, weights: torch.Tensor, means: torch.Tensor,
                covariances: torch.Tensor) -> torch.Tensor:
    """Density ``ĝ(x) = Σ_j α_j 𝒩(x | μ_j, Σ_j)`` at points ``x (*B, M, D)`` -> ``(*B, M)``.

    The mixture is ``weights (*B, J)``, ``means (*B, J, D)``, ``covariances (*B, J, D, D)`` (positive
    definite); batch dims broadcast, so a shared set of points ``(M, D)`` works with a batch of mixtures.
    """
    fn = "gmm_density"
    D = _check_gmm(weights, means, covariances, fn)
    x = _tensor(x, "x", fn, 2)
    if x.shape[-1] != D:
        raise ValueError(f"{fn}: argument 'x' must be (*B, M, D) with D = {D}, got {tuple(x.shape)}")
    check_same_device(fn, x=x, means=means)
    chol = torch.linalg.cholesky(covariances)                          # (*B, J, D, D)
    diff = x[..., :, None, :] - means[..., None, :, :]                 # (*B, M, J, D)
    shape = torch.broadcast_shapes(diff.shape[:-1], chol.shape[:-3] + (1,) + chol.shape[-3:-2])
    Lb = chol[..., None, :, :, :].expand(*shape, D, D)
    z = torch.linalg.solve_triangular(Lb, diff.expand(*shape, D)[..., None], upper=False)[..., 0]
    logdet = torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)  # (*B, J)
    logn = -0.5 * (z * z).sum(-1) - logdet[..., None, :] - 0.5 * D * math.log(2.0 * math.pi)
    return (weights[..., None, :] * torch.exp(logn)).sum(-1)


def running_coefficients(traj: torch.Tensor, *, n_basis: int, length: float) -> torch.Tensor:
    """Time-averaged coefficients ``w_t = 1/(N t) Σ_{s≤t} Σ_i φ(x_{s,i})`` (Eq. 127/135/145) at every step.

    Args:
        traj: ``(*B, T, N, D)`` (``N`` agents sharing the coefficients; ``N = 1`` for one agent).

    Returns:
        ``(*B, T, K^D)``; ``[..., -1, :]`` is the average over the whole trajectory.
    """
    traj = _agents(_tensor(traj, "traj", "running_coefficients", 3), "traj", "running_coefficients")
    phi = fourier_basis(traj, n_basis=n_basis, length=length).mean(-2)   # (*B, T, K^D)
    t = torch.arange(1, traj.shape[-3] + 1, dtype=traj.dtype, device=traj.device)
    return phi.cumsum(-2) / t[:, None]


def ergodic_metric(w: torch.Tensor, w_hat: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """``ε = ½ Σ_k Λ_k (w_k − ŵ_k)² = ½ (w − ŵ)ᵀ Λ (w − ŵ)`` (Eq. 129/134, 147-148).

    Args:
        w, w_hat: ``(*B, K^D)`` (broadcast).
        weights: ``Λ (K^D,)`` or ``(*B, K^D)``, e.g. :func:`sobolev_weights`.

    Returns:
        ``(*B,)``.
    """
    fn = "ergodic_metric"
    for n, v in (("w", w), ("w_hat", w_hat), ("weights", weights)):
        _tensor(v, n, fn)
    check_same_device(fn, w=w, w_hat=w_hat, weights=weights)
    if not (w.shape[-1] == w_hat.shape[-1] == weights.shape[-1]):
        raise ValueError(f"{fn}: 'w', 'w_hat', 'weights' must share the last dim K^D, got "
                         f"{tuple(w.shape)}, {tuple(w_hat.shape)}, {tuple(weights.shape)}")
    e = w - w_hat
    return 0.5 * (weights * e * e).sum(-1)


# ----------------------------------------------------------------------------------------------------------
# SMC: myopic controller (§10.1.1 Eq. 131-138, §10.1.2 Eq. 157-159)

class SMCState(NamedTuple):
    """State of the myopic SMC controller.

    x: agent positions ``(*B, N, D)``.  coeff_sum: ``Σ_{s} Σ_i φ(x_{s,i})`` over the steps taken so far
    ``(*B, K^D)``.  n_steps: how many steps were accumulated (``w = coeff_sum / (N n_steps)``).
    """

    x: torch.Tensor
    coeff_sum: torch.Tensor
    n_steps: int


class SMCStep(NamedTuple):
    """One step: the next ``state``, the command ``u (*B, N, D)`` applied, the coefficients ``w`` that
    include the positions the step started from ``(*B, K^D)`` and their metric ``(*B,)``."""

    state: SMCState
    u: torch.Tensor
    w: torch.Tensor
    metric: torch.Tensor


class SMCRollout(NamedTuple):
    """``x (*B, T, N, D)``: the positions averaged (``x_1..x_T``); ``x_final (*B, N, D)``: where the last
    command leads; ``u (*B, T, N, D)``; ``metric (*B, T)``: ``ε`` of the coefficients after each step;
    ``w (*B, K^D)``: the final time-averaged coefficients; ``state``: to continue the rollout."""

    x: torch.Tensor
    x_final: torch.Tensor
    u: torch.Tensor
    metric: torch.Tensor
    w: torch.Tensor
    state: SMCState


def smc_init(x0: torch.Tensor, *, n_basis: int) -> SMCState:
    """Initial state for agents at ``x0 (*B, N, D)``, with no coefficients accumulated yet."""
    x0 = _agents(_tensor(x0, "x0", "smc_init", 2), "x0", "smc_init")
    K = _pos_int(n_basis, "n_basis", "smc_init")
    zeros = x0.new_zeros(x0.shape[:-2] + (K ** x0.shape[-1],))
    return SMCState(x0, zeros, 0)


def smc_control(x: torch.Tensor, w: torch.Tensor, w_hat: torch.Tensor, weights: torch.Tensor, *,
                n_basis: int, length: float, u_max: float) -> torch.Tensor:
    """Myopic SMC command ``u = u_max ũ/‖ũ‖``, ``ũ = −∇_x φ(x)ᵀ Λ (w − ŵ)`` (Eq. 138, 159).

    In 1-D this is ``sign(ũ) u_max``.  Where ``ũ = 0`` (e.g. ``w = ŵ``) the command is ``0``, so
    ``‖u‖ ≤ u_max`` always.

    Args:
        x: ``(*B, N, D)``; w, w_hat: ``(*B, K^D)`` shared by the agents;
        weights: ``Λ (K^D,)``.

    Returns:
        ``u`` with the shape of ``x``.
    """
    fn = "smc_control"
    x, D, K, ell = _basis_args(x, n_basis, length, fn)
    if x.dim() < 2:
        raise ValueError(f"{fn}: argument 'x' must be (*B, N, D) (N agents), got {tuple(x.shape)}")
    umax = _pos_float(u_max, "u_max", fn)
    for n, v in (("w", w), ("w_hat", w_hat), ("weights", weights)):
        _tensor(v, n, fn)
        _check_coeffs(v, n, fn, K ** D)
    check_same_device(fn, x=x, w=w, w_hat=w_hat, weights=weights)
    g = fourier_basis_grad(x, n_basis=K, length=ell)                   # (*B, N, K^D, D)
    r = (weights * (w - w_hat))[..., None, :, None]                     # (*B, 1, K^D, 1)
    u_tilde = -(g * r).sum(-2)
    return _safe_normalize(u_tilde, umax)


def smc_step(state: SMCState, w_hat: torch.Tensor, weights: torch.Tensor, *, n_basis: int, length: float,
             u_max: float, dt: float) -> SMCStep:
    """One step of the myopic SMC controller on ``ẋ = u`` (Eq. 131/157).

    Adds ``φ`` at the current positions of all agents to the shared running sum (Eq. 145, computed
    recursively), computes ``u`` (:func:`smc_control`) and moves ``x ← x + Δt u``.
    """
    fn = "smc_step"
    if not isinstance(state, SMCState):
        raise TypeError(f"{fn}: argument 'state' must be an SMCState (from smc_init), got "
                        f"{type(state).__name__}")
    dt = _pos_float(dt, "dt", fn)
    x = _agents(_tensor(state.x, "state.x", fn, 2), "state.x", fn)
    N = x.shape[-2]
    coeff_sum = state.coeff_sum + fourier_basis(x, n_basis=n_basis, length=length).sum(-2)
    n = state.n_steps + 1
    w = coeff_sum / (N * n)
    u = smc_control(x, w, w_hat, weights, n_basis=n_basis, length=length, u_max=u_max)
    return SMCStep(SMCState(x + dt * u, coeff_sum, n), u, w, ergodic_metric(w, w_hat, weights))


def smc_rollout(x0: torch.Tensor, w_hat: torch.Tensor, *, n_steps: int, dt: float, u_max: float,
                n_basis: int, length: float, weights: torch.Tensor | None = None,
                state: SMCState | None = None) -> SMCRollout:
    """Run the myopic SMC controller for ``T = n_steps`` steps (a loop over time only).

    Args:
        x0: ``(*B, N, D)`` initial positions of ``N`` agents (ignored when ``state`` is given).
        w_hat: target coefficients ``(*B, K^D)`` (e.g. :func:`gmm_fourier_coefficients`); batch dims
            broadcast with those of ``x0``.
        weights: ``Λ (K^D,)``; default :func:`sobolev_weights` (Eq. 149).
        state: continue from a previous rollout's ``state`` instead of starting at ``x0``.

    Returns:
        :class:`SMCRollout`.
    """
    fn = "smc_rollout"
    T = _pos_int(n_steps, "n_steps", fn)
    if state is None:
        state = smc_init(x0, n_basis=n_basis)
    x = _agents(_tensor(state.x, "x0", fn, 2), "x0" if x0 is state.x else "state.x", fn)
    w_hat = _tensor(w_hat, "w_hat", fn)
    if weights is None:
        weights = sobolev_weights(x.shape[-1], _pos_int(n_basis, "n_basis", fn), dtype=x.dtype,
                                  device=x.device)
    batch = torch.broadcast_shapes(x.shape[:-2], w_hat.shape[:-1])
    state = SMCState(state.x.expand(*batch, *x.shape[-2:]),
                     state.coeff_sum.expand(*batch, state.coeff_sum.shape[-1]), state.n_steps)
    xs, us, ms = [], [], []
    for _ in range(T):
        xs.append(state.x)
        step = smc_step(state, w_hat, weights, n_basis=n_basis, length=length, u_max=u_max, dt=dt)
        state = step.state
        us.append(step.u)
        ms.append(step.metric)
    return SMCRollout(torch.stack(xs, -3), state.x, torch.stack(us, -3), torch.stack(ms, -1), step.w, state)


# ----------------------------------------------------------------------------------------------------------
# SMC as a planning problem (§10.1.1 Eq. 139-142; §10.1.2, Fig. 43)

class SMCPlan(NamedTuple):
    """Result of :func:`smc_plan`.

    u: commands ``(*B, T, N, D)``; x: positions ``x_1..x_T`` ``(*B, T, N, D)``; metric: ``ε`` of the plan
    ``(*B,)`` (Eq. 147); cost: ``c = fᵀ Λ f + r ‖u‖²`` (Eq. 139) ``(*B,)``; cost_history: ``(*B, I+1)``
    (the cost after each iteration, kept when a step is rejected); gradient_norm: ``‖∇_u c‖∞`` at the
    returned ``u`` ``(*B,)``; converged: that gradient was checked below ``tol`` relative to its value at
    ``u_init`` ``(*B,)``; iterations: Gauss-Newton steps accepted ``(*B,)``.
    """

    u: torch.Tensor
    x: torch.Tensor
    metric: torch.Tensor
    cost: torch.Tensor
    cost_history: torch.Tensor
    gradient_norm: torch.Tensor
    converged: torch.Tensor
    iterations: torch.Tensor


def smc_plan(x0: torch.Tensor, u_init: torch.Tensor, w_hat: torch.Tensor, *, dt: float, n_basis: int,
             length: float, control_weight: float = 1e-6, weights: torch.Tensor | None = None,
             max_iter: int = 50, tol: float = 1e-4, n_line_search: int = 12) -> SMCPlan:
    """SMC as a planning problem: Gauss-Newton on the whole command sequence (Eq. 139-142).

    Agents ``ẋ = u`` discretized as ``x_{s} = x_0 + Δt Σ_{r<s} u_r`` (``x = S_x x_0 + S_u u``, Appendix A),
    ``s = 1..T``.  The cost ``c(u) = f(x)ᵀ Q f(x) + uᵀ R u`` (Eq. 139), ``Q = Λ``, ``R = r I``,
    ``f = w(x) − ŵ``, ``w(x) = 1/(T N) Σ_s Σ_i φ(x_{s,i})`` (Eq. 140; ``N`` agents share ``w``) is not a sum
    of per-step costs, so the iteration is the batch form of the seed (Eq. 141)::

        Δu = −(S_uᵀ Jᵀ Q J S_u + R)⁻¹ (S_uᵀ Jᵀ Q f + R u),   J = 1/(T N) [∇φ(x_1), ..., ∇φ(x_T)] (Eq. 142)

    with ``J S_u`` computed as a reverse cumulative sum over time (never forming ``S_u``), and a
    backtracking line search (step sizes ``1, ½, ...``, all tried at once; a step is taken only where the
    cost decreases).  Per-element status: ``converged`` where ``‖∇_u c‖∞ ≤ tol ‖∇_u c(u_init)‖∞``
    at the returned point.  An element with non-finite inputs is left as it is (not converged) and does not
    affect the others.  A good ``u_init`` is the myopic controller's (:func:`smc_rollout`), as in Fig. 43.

    Args:
        x0: ``(*B, N, D)``; u_init: ``(*B, T, N, D)``; w_hat: ``(*B, K^D)``.
        control_weight: ``r > 0``.
        weights: ``Λ (K^D,)``; default :func:`sobolev_weights`.

    Returns:
        :class:`SMCPlan`.
    """
    fn = "smc_plan"
    x0 = _agents(_tensor(x0, "x0", fn, 2), "x0", fn)
    u = _tensor(u_init, "u_init", fn, 3)
    w_hat = _tensor(w_hat, "w_hat", fn)
    dt = _pos_float(dt, "dt", fn)
    K = _pos_int(n_basis, "n_basis", fn)
    ell = _pos_float(length, "length", fn)
    r = _pos_float(control_weight, "control_weight", fn)
    iters = _pos_int(max_iter, "max_iter", fn, minimum=0)
    n_ls = _pos_int(n_line_search, "n_line_search", fn)
    tol = _pos_float(tol, "tol", fn)
    N, D = x0.shape[-2:]
    if u.shape[-2:] != (N, D):
        raise ValueError(f"{fn}: argument 'u_init' must be (*B, T, N, D) = (*B, T, {N}, {D}) to match 'x0', "
                         f"got {tuple(u.shape)}")
    _check_coeffs(w_hat, "w_hat", fn, K ** D)
    if weights is None:
        weights = sobolev_weights(D, K, dtype=x0.dtype, device=x0.device)
    check_same_device(fn, x0=x0, u_init=u, w_hat=w_hat, weights=weights)
    T = u.shape[-3]
    batch = torch.broadcast_shapes(x0.shape[:-2], u.shape[:-3], w_hat.shape[:-1])
    x0 = x0.expand(*batch, N, D)
    u = u.expand(*batch, T, N, D)
    w_hat = w_hat.expand(*batch, K ** D)
    n = T * N * D
    eye = torch.eye(n, dtype=u.dtype, device=u.device)

    def positions(uu, xx0=x0):
        return xx0[..., None, :, :] + dt * uu.cumsum(-3)

    def cost_of(uu, wh, xx0=x0):
        f = fourier_basis(positions(uu, xx0), n_basis=K, length=ell).mean((-3, -2)) - wh
        return (weights * f * f).sum(-1) + r * (uu * uu).flatten(-3).sum(-1), f

    def linear(uu):
        c, f = cost_of(uu, w_hat)
        Js = fourier_basis_grad(positions(uu), n_basis=K, length=ell) / (T * N)   # (*B, T, N, K^D, D)
        G = dt * Js.flip(-4).cumsum(-4).flip(-4)                                 # ∂f/∂u_r = Δt Σ_{s>r} J_s
        G = G.permute(*range(G.dim() - 4), -2, -4, -3, -1).reshape(*batch, K ** D, n)
        g = (G.mT @ (weights * f)[..., None])[..., 0] + r * uu.reshape(*batch, n)  # ½ ∇_u c
        return c, G, g

    finite = torch.isfinite(x0).flatten(-2).all(-1) & torch.isfinite(u).flatten(-3).all(-1) \
        & torch.isfinite(w_hat).all(-1)
    c, G, g = linear(u)
    g0 = g.abs().amax(-1)
    history = [c]
    accepted = torch.zeros(batch, dtype=torch.long, device=u.device)
    alphas = 0.5 ** torch.arange(n_ls, dtype=u.dtype, device=u.device)
    for _ in range(iters):
        done = g.abs().amax(-1) <= tol * g0
        H = G.mT @ (weights[..., :, None] * G) + r * eye                          # Eq. 141
        ok = finite & ~done
        H = torch.where(ok[..., None, None], H, eye)
        rhs = torch.where(ok[..., None], g, torch.zeros_like(g))
        L, _ = torch.linalg.cholesky_ex(H)
        du = -torch.cholesky_solve(rhs[..., None], L)[..., 0].reshape(*batch, T, N, D)
        cand = u[..., None, :, :, :] + alphas[:, None, None, None] * du[..., None, :, :, :]
        cc, _ = cost_of(cand, w_hat[..., None, :], x0[..., None, :, :])          # (*B, n_ls)
        better = cc < c[..., None]
        first = torch.where(better.any(-1), better.to(torch.int8).argmax(-1), n_ls)
        take = ok & (first < n_ls)
        idx = first.clamp(max=n_ls - 1)
        pick = idx[..., None, None, None, None].expand(*batch, 1, T, N, D)
        u_new = torch.gather(cand, -4, pick)[..., 0, :, :, :]
        u = torch.where(take[..., None, None, None], u_new, u)
        accepted = accepted + take.long()
        c, G, g = linear(u)
        history.append(c)
    gnorm = 2.0 * g.abs().amax(-1)
    converged = finite & (g.abs().amax(-1) <= tol * g0)
    x = positions(u)
    w = fourier_basis(x, n_basis=K, length=ell).mean((-3, -2))
    return SMCPlan(u, x, ergodic_metric(w, w_hat, weights), c, torch.stack(history, -1), gnorm, converged,
                   accepted)


# ----------------------------------------------------------------------------------------------------------
# HEDAC (§10.2)

@dataclass(frozen=True)
class HeatGrid:
    """Cell-centred grid of ``n_cells = G`` cells per dimension on ``[0, ℓ]^D``; spacing ``h = ℓ/G``.

    Fields on it are ``(*B, G, ..., G)`` with ``D`` trailing grid dims.
    """

    n_dims: int
    n_cells: int
    length: float

    def __post_init__(self) -> None:
        _pos_int(self.n_dims, "n_dims", "HeatGrid")
        _pos_int(self.n_cells, "n_cells", "HeatGrid", minimum=3)
        _pos_float(self.length, "length", "HeatGrid")

    @property
    def spacing(self) -> float:
        return self.length / self.n_cells

    @property
    def cell_volume(self) -> float:
        return self.spacing ** self.n_dims

    @property
    def field_shape(self) -> tuple[int, ...]:
        return (self.n_cells,) * self.n_dims

    def points(self, *, dtype: torch.dtype = torch.float64,
               device: torch.device | str | None = None) -> torch.Tensor:
        """Cell centres ``(G, ..., G, D)`` (row-major, coordinate ``d`` along grid dim ``d``)."""
        c = (torch.arange(self.n_cells, dtype=dtype, device=device) + 0.5) * self.spacing
        return torch.stack(torch.meshgrid(*([c] * self.n_dims), indexing="ij"), dim=-1)

    def check_field(self, f, name: str, fn: str) -> torch.Tensor:
        f = _tensor(f, name, fn, self.n_dims)
        if tuple(f.shape[f.dim() - self.n_dims:]) != self.field_shape:
            dims = ", ".join(["G"] * self.n_dims)
            raise ValueError(f"{fn}: argument '{name}' must be a field (*B, {dims}) with G = {self.n_cells}, "
                             f"got {tuple(f.shape)}")
        return f

    def integrate(self, f: torch.Tensor) -> torch.Tensor:
        """``∫_Ω f dx ≈ h^D Σ f`` over the grid dims: ``(*B, G..G) -> (*B,)``."""
        return f.flatten(f.dim() - self.n_dims).sum(-1) * self.cell_volume

    def normalize(self, f: torch.Tensor) -> torch.Tensor:
        """``f / ∫ f`` (Eq. 162); ``0`` where ``∫ f = 0``."""
        z = self.integrate(f)[(...,) + (None,) * self.n_dims]
        zero = z == 0                                                  # NaN stays NaN
        return torch.where(zero, torch.zeros_like(f), f / torch.where(zero, torch.ones_like(z), z))


class HEDACState(NamedTuple):
    """x: agent positions ``(*B, N, D)``; coverage: ``Σ_s Δt Σ_i φ(x − x_i(s))`` on the grid (Eq. 166,
    unnormalized) ``(*B, G..G)``; heat: the temperature field ``u`` ``(*B, G..G)``; n_steps: steps taken."""

    x: torch.Tensor
    coverage: torch.Tensor
    heat: torch.Tensor
    n_steps: int


class HEDACStep(NamedTuple):
    """The next ``state``; the velocity ``v (*B, N, D)`` applied; the normalized coverage ``c`` and the
    residual norm ``‖e‖ = (∫ (p − c)²)^{1/2}`` ``(*B,)`` after adding the current positions."""

    state: HEDACState
    v: torch.Tensor
    coverage: torch.Tensor
    residual_norm: torch.Tensor


class HEDACRollout(NamedTuple):
    """``x (*B, T, N, D)``: positions whose footprints were added; ``x_final (*B, N, D)``;
    ``residual_norm (*B, T)``; ``coverage (*B, G..G)``: the final normalized coverage ``c``;
    ``state``: to continue."""

    x: torch.Tensor
    x_final: torch.Tensor
    residual_norm: torch.Tensor
    coverage: torch.Tensor
    state: HEDACState


def _laplacian(u: torch.Tensor, grid: HeatGrid) -> torch.Tensor:
    """Five-point (2D+1-point) Laplacian with insulated walls (ghost cells mirror the edge, Eq. 165)."""
    out = torch.zeros_like(u)
    nd = u.dim()
    for d in range(grid.n_dims):
        dim = nd - grid.n_dims + d
        first, last = u.narrow(dim, 0, 1), u.narrow(dim, grid.n_cells - 1, 1)
        p = torch.cat([first, u, last], dim)
        out = out + p.narrow(dim, 2, grid.n_cells) + p.narrow(dim, 0, grid.n_cells) - 2.0 * u
    return out / grid.spacing ** 2


def heat_step(u: torch.Tensor, source: torch.Tensor, grid: HeatGrid, *, alpha: float, dt: float,
              cooling: float = 0.0) -> torch.Tensor:
    """One explicit Euler step of ``∂u/∂t = α Δu − β u + s`` with ``∂u/∂n = 0`` on the walls (Eq. 165).

    ``β = cooling = 0`` (the default) is Eq. 163 exactly; ``β > 0`` is the cooling term of the HEDAC
    paper the seed cites ([6]), which lets heat left behind in covered regions fade.  With ``β = 0`` the
    discrete Laplacian conserves ``Σ u`` exactly, so ``∫ u`` grows by ``Δt ∫ s`` per step.  Stable and
    monotone for ``Δt (2Dα/h² + β) ≤ 1``; a larger step raises (use several sub-steps, as
    :func:`hedac_step` does).

    Args:
        u, source: fields ``(*B, G..G)`` (broadcast).

    Returns:
        ``(*B, G..G)``.
    """
    fn = "heat_step"
    a = _pos_float(alpha, "alpha", fn, allow_zero=True)
    dt = _pos_float(dt, "dt", fn)
    u = grid.check_field(u, "u", fn)
    source = grid.check_field(source, "source", fn)
    check_same_device(fn, u=u, source=source)
    b = _pos_float(cooling, "cooling", fn, allow_zero=True)
    r = dt * (2 * grid.n_dims * a / grid.spacing ** 2 + b)
    if r > 1.0 + 1e-12:
        raise ValueError(f"{fn}: explicit step unstable: dt*(2D*alpha/h^2 + cooling) = {r:.4g} > 1; "
                         "reduce 'dt' or use more sub-steps")
    out = u + dt * (a * _laplacian(u, grid) + source)
    return out - (dt * b) * u if b > 0 else out


def hedac_source(target: torch.Tensor, coverage: torch.Tensor, grid: HeatGrid) -> torch.Tensor:
    """Heat source ``s = max(e, 0)² / ∫ max(e, 0)²``, ``e = p − c`` (Eq. 160-162); ``(*B, G..G)``.

    ``target`` ``p`` and ``coverage`` ``c`` are normalized densities on the grid; ``s = 0`` where
    ``e ≤ 0`` everywhere.
    """
    fn = "hedac_source"
    target = grid.check_field(target, "target", fn)
    coverage = grid.check_field(coverage, "coverage", fn)
    check_same_device(fn, target=target, coverage=coverage)
    return grid.normalize(torch.clamp(target - coverage, min=0.0) ** 2)


def agent_footprint(x: torch.Tensor, grid: HeatGrid, *, shape: float) -> torch.Tensor:
    """Sum over agents of the footprints ``φ(y − x_i) = exp(−(ε ‖y − x_i‖)²)`` (Eq. 167) on the grid.

    Args:
        x: ``(*B, N, D)``.
        shape: ``ε > 0``.

    Returns:
        ``(*B, G..G)``.
    """
    fn = "agent_footprint"
    x = _tensor(x, "x", fn, 2)
    eps = _pos_float(shape, "shape", fn)
    if x.shape[-1] != grid.n_dims:
        raise ValueError(f"{fn}: argument 'x' must be (*B, N, D) with D = {grid.n_dims}, got "
                         f"{tuple(x.shape)}")
    pts = grid.points(dtype=x.dtype, device=x.device).reshape(-1, grid.n_dims)   # (M, D)
    d2 = ((pts - x[..., :, None, :]) ** 2).sum(-1)                              # (*B, N, M)
    f = torch.exp(-(eps * eps) * d2).sum(-2)
    return f.reshape(*f.shape[:-1], *grid.field_shape)


def field_gradient_at(u: torch.Tensor, x: torch.Tensor, grid: HeatGrid) -> torch.Tensor:
    """``∇u(x_i)`` (Eq. 164): central differences on the grid (one-sided at the walls), interpolated
    multilinearly at the agent positions (clamped to the cell centres' hull).

    Args:
        u: ``(*B, G..G)``; x: ``(*B, N, D)``.

    Returns:
        ``(*B, N, D)``.
    """
    fn = "field_gradient_at"
    u = grid.check_field(u, "u", fn)
    x = _tensor(x, "x", fn, 2)
    D, G, h = grid.n_dims, grid.n_cells, grid.spacing
    if x.shape[-1] != D:
        raise ValueError(f"{fn}: argument 'x' must be (*B, N, D) with D = {D}, got {tuple(x.shape)}")
    check_same_device(fn, u=u, x=x)
    dims = tuple(range(u.dim() - D, u.dim()))
    grads = torch.stack(torch.gradient(u, spacing=h, dim=dims), -1)   # (*B, G..G, D)
    flat = grads.flatten(u.dim() - D, u.dim() - 1)                     # (*B, M, D)
    q = (x / h - 0.5).clamp(0.0, G - 1.0)
    qd = q.detach()
    qd = torch.where(torch.isfinite(qd), qd, torch.zeros_like(qd))   # a NaN agent reads cell 0, stays NaN
    i0 = torch.floor(qd).clamp(0, G - 2).long()                       # (*B, N, D)
    frac = q - i0.to(q.dtype)
    batch = torch.broadcast_shapes(flat.shape[:-2], x.shape[:-2])
    flat = flat.expand(*batch, *flat.shape[-2:])
    strides = torch.tensor([G ** (D - 1 - d) for d in range(D)], device=x.device)
    corners = torch.tensor([[(c >> (D - 1 - d)) & 1 for d in range(D)] for c in range(2 ** D)],
                           device=x.device)                                          # (C, D)
    N = x.shape[-2]
    idx = ((i0[..., None, :, :] + corners[:, None, :]) * strides).sum(-1)            # (*B, C, N)
    wgt = torch.where(corners[:, None, :].bool(), frac[..., None, :, :],
                      1.0 - frac[..., None, :, :]).prod(-1)                          # (*B, C, N)
    idx = idx.expand(*batch, 2 ** D, N).flatten(-2)                                  # (*B, C N)
    vals = torch.gather(flat, -2, idx[..., None].expand(*batch, 2 ** D * N, D))
    vals = vals.unflatten(-2, (2 ** D, N))                                           # (*B, C, N, D)
    return (wgt[..., None] * vals).sum(-3)


def hedac_init(x0: torch.Tensor, grid: HeatGrid) -> HEDACState:
    """Agents at ``x0 (*B, N, D)``, zero coverage and zero temperature."""
    x0 = _agents(_tensor(x0, "x0", "hedac_init", 2), "x0", "hedac_init")
    if x0.shape[-1] != grid.n_dims:
        raise ValueError(f"hedac_init: argument 'x0' must be (*B, N, D) with D = {grid.n_dims}, got "
                         f"{tuple(x0.shape)}")
    z = x0.new_zeros(x0.shape[:-2] + grid.field_shape)
    return HEDACState(x0, z, z, 0)


def hedac_step(state: HEDACState, target: torch.Tensor, grid: HeatGrid, *, alpha: float, dt: float,
               u_max: float, shape: float, cooling: float = 0.0, n_substeps: int | None = None
               ) -> HEDACStep:
    """One HEDAC step (§10.2).

    1. add the footprints at the current positions to the coverage (Eq. 166-167, ``Δt`` per step) and
       normalize the total (Eq. 168 then 162): ``c``;
    2. source ``s`` from the residual ``e = p − c`` (Eq. 160-162);
    3. diffuse: ``n_substeps`` explicit steps of Eq. 163 over ``Δt`` (default: the fewest that are
       stable, :func:`heat_step`; fewer than stable raises a ``ValueError`` naming ``n_substeps``), with the
       optional cooling ``−β u`` of [6] (``cooling = β``, default 0);
    4. move every agent along ``∇u(x_i)`` (Eq. 164) at speed ``u_max`` (velocity control, as in SMC),
       ``x ← clamp(x + Δt v, 0, ℓ)`` (the walls of the domain).

    Args:
        target: ``p (*B, G..G)``, a density on the grid (normalized here, Eq. 162).
    """
    fn = "hedac_step"
    if not isinstance(state, HEDACState):
        raise TypeError(f"{fn}: argument 'state' must be a HEDACState (from hedac_init), got "
                        f"{type(state).__name__}")
    dt = _pos_float(dt, "dt", fn)
    a = _pos_float(alpha, "alpha", fn)
    umax = _pos_float(u_max, "u_max", fn)
    target = grid.check_field(target, "target", fn)
    check_same_device(fn, x=state.x, target=target)
    b = _pos_float(cooling, "cooling", fn, allow_zero=True)
    if n_substeps is None:
        n_substeps = max(1, math.ceil(dt * (2 * grid.n_dims * a / grid.spacing ** 2 + b) / 0.95))
    n_sub = _pos_int(n_substeps, "n_substeps", fn)
    r = (dt / n_sub) * (2 * grid.n_dims * a / grid.spacing ** 2 + b)
    if r > 1.0 + 1e-12:
        need = math.ceil(dt * (2 * grid.n_dims * a / grid.spacing ** 2 + b))
        raise ValueError(f"{fn}: argument 'n_substeps' = {n_sub} is too few for a stable explicit heat step: "
                         f"(dt/n_substeps)*(2D*alpha/h^2 + cooling) = {r:.4g} > 1; use n_substeps >= {need} "
                         "(or None for the default)")
    _agents(_tensor(state.x, "state.x", fn, 2), "state.x", fn)
    p = grid.normalize(target)
    coverage = state.coverage + dt * agent_footprint(state.x, grid, shape=shape)
    c = grid.normalize(coverage)
    s = hedac_source(p, c, grid)
    u = state.heat
    for _ in range(n_sub):
        u = heat_step(u, s, grid, alpha=a, dt=dt / n_sub, cooling=b)
    v = _safe_normalize(field_gradient_at(u, state.x, grid), umax)
    x = (state.x + dt * v).clamp(0.0, grid.length)
    res = grid.integrate((p - c) ** 2).sqrt()
    return HEDACStep(HEDACState(x, coverage, u, state.n_steps + 1), v, c, res)


def hedac_rollout(x0: torch.Tensor, target: torch.Tensor, grid: HeatGrid, *, n_steps: int, alpha: float,
                  dt: float, u_max: float, shape: float, cooling: float = 0.0, n_substeps: int | None = None,
                  state: HEDACState | None = None) -> HEDACRollout:
    """Run :func:`hedac_step` for ``T = n_steps`` steps (a loop over time only).

    Args:
        x0: ``(*B, N, D)``, ``N`` agents per problem (ignored when ``state`` is given).
        target: ``p (*B, G..G)``; batch dims broadcast with those of ``x0``.

    Returns:
        :class:`HEDACRollout`.
    """
    fn = "hedac_rollout"
    T = _pos_int(n_steps, "n_steps", fn)
    if state is None:
        state = hedac_init(x0, grid)
    target = grid.check_field(target, "target", fn)
    batch = torch.broadcast_shapes(state.x.shape[:-2], target.shape[:target.dim() - grid.n_dims],
                                   state.coverage.shape[:state.coverage.dim() - grid.n_dims])
    f = (*batch, *grid.field_shape)
    state = HEDACState(state.x.expand(*batch, *state.x.shape[-2:]), state.coverage.expand(f),
                       state.heat.expand(f), state.n_steps)
    xs, rs = [], []
    for _ in range(T):
        xs.append(state.x)
        step = hedac_step(state, target, grid, alpha=alpha, dt=dt, u_max=u_max, shape=shape, cooling=cooling,
                          n_substeps=n_substeps)
        state = step.state
        rs.append(step.residual_norm)
    return HEDACRollout(torch.stack(xs, -3), state.x, torch.stack(rs, -1), step.coverage, state)
