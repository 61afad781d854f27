"""Linear MPC about the current state: the first control of the finite-horizon LQ problem on a model
linearized once per step — the cheapest MPC step there is for a model whose Jacobians are expensive (a
MuJoCo model by finite differences: one batched call per step instead of thousands of steps per iLQR
iteration).

At the current state ``x̄`` and a control ``ū`` (the last one applied) the model is
``x_{t+1} ≈ A x_t + B u_t + c`` with ``A = ∂f/∂x``, ``B = ∂f/∂u`` and ``c = f(x̄, ū) − A x̄ − B ū``, held
over the whole horizon.  The cost is this package's quadratic form (no ½, :mod:`controllers.costs`)::

    Σ_{t<T} (x_t − x_r)ᵀQ_t(x_t − x_r) + (u_t − u_r)ᵀR_t(u_t − u_r) + (x_T − x_r)ᵀQ_T(x_T − x_r)

written on ``z = [x; 1]`` as a plain LQR (``z' = Ã z + B̃ u`` with ``Ã = [[A, c], [0, 1]]``,
``B̃ = [B; 0]``, state weight ``Q̃ = [[Q, −Q x_r], [−x_rᵀQ, x_rᵀQ x_r]]``, cross weight ``Ñ = [0; −u_rᵀR]``),
the value ``V_t(z) = zᵀP_t z`` follows the Riccati recursion from ``P_T = Q̃_T``::

    H = R_t + B̃ᵀP B̃,   G = H⁻¹ (B̃ᵀP Ã + Ñᵀ),   u_t = −G z_t
    P ← Q̃_t + ÃᵀP Ã − (B̃ᵀP Ã + Ñᵀ)ᵀ G

(about ten small matrix operations a step).  The first control ``u_0 = −G_0 [x̄; 1]`` is the exact
minimizer of the linearized problem without limits; :func:`linear_mpc_action` then clips it to the limits
(saturated LQ, not a box-constrained QP: where the limits bind along the horizon the plan is not the
constrained optimum).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["lq_first_action", "linear_mpc_action"]


def lq_first_action(A: Tensor, B: Tensor, c: Tensor, Q: Tensor, R: Tensor, x_ref: Tensor, u_ref: Tensor,
                    x0: Tensor, horizon: int) -> tuple[Tensor, Tensor]:
    """``(u_0 (*B, m), K_0 (*B, m, n))`` of the time-invariant LQ problem above (module docstring).

    Args:
        A, B, c: ``(*B, n, n)``, ``(*B, n, m)``, ``(*B, n)``.
        Q: ``(T+1, n, n)`` or ``(1, n, n)`` (then the same at every time, the terminal one included);
            R: ``(T, m, m)`` or ``(1, m, m)``; x_ref ``(n,)``, u_ref ``(m,)``.
        x0: ``(*B, n)``; horizon: ``T >= 1``.
    """
    if not isinstance(horizon, int) or isinstance(horizon, bool) or horizon < 1:
        raise ValueError(f"lq_first_action: argument 'horizon' must be a positive int, got {horizon!r}")
    # the affine problem as a plain LQR on z = [x; 1]: z' = Ã z + B̃ u, cost zᵀQ̃z + uᵀRu + 2 zᵀÑu (+ const)
    bs, n, m = A.shape[:-2], A.shape[-1], B.shape[-1]
    At = torch.cat([torch.cat([A, c.unsqueeze(-1)], -1),
                    torch.cat([torch.zeros(*bs, 1, n, dtype=A.dtype, device=A.device),
                               torch.ones(*bs, 1, 1, dtype=A.dtype, device=A.device)], -1)], -2)
    Bt = torch.cat([B, torch.zeros(*bs, 1, m, dtype=B.dtype, device=B.device)], -2)
    Ata, Bta = At.transpose(-1, -2), Bt.transpose(-1, -2)

    def q_aug(Qt):
        qx = -(Qt @ x_ref)
        top = torch.cat([Qt, qx.unsqueeze(-1)], -1)
        return torch.cat([top, torch.cat([qx, (x_ref @ qx).neg().reshape(1)]).unsqueeze(-2)], -2)

    Qa = [q_aug(Q[i]) for i in range(Q.shape[0])]
    Ns = [torch.cat([torch.zeros(m, n, dtype=A.dtype, device=A.device), -(R[i] @ u_ref).unsqueeze(-1)], -1)
          for i in range(R.shape[0])]  # Ñᵀ (m, n+1)
    P = Qa[-1]
    G = None
    for t in reversed(range(horizon)):
        Rt, Nt = R[min(t, R.shape[0] - 1)], Ns[min(t, len(Ns) - 1)]
        BtP = Bta @ P
        H = Rt + BtP @ Bt
        G = torch.linalg.solve(H, BtP @ At + Nt) if m > 1 else (BtP @ At + Nt) / H
        P = Qa[min(t, len(Qa) - 1)] + Ata @ P @ At - (BtP @ At + Nt).transpose(-1, -2) @ G
    K, k = G[..., :n], -G[..., n]
    u0 = k - (K @ x0.unsqueeze(-1)).squeeze(-1)
    return u0, K


def linear_mpc_action(system, x: Tensor, u_bar: Tensor, Q: Tensor, R: Tensor, x_ref: Tensor, u_ref: Tensor,
                      horizon: int, lower: Tensor | None = None, upper: Tensor | None = None) -> Tensor:
    """The linear MPC's control ``(*B, m)`` at states ``x (*B, n)``: ``system`` linearized at ``(x, u_bar)``
    (its ``jacobian`` and one ``step``: two batched calls), :func:`lq_first_action`, clipped to the limits."""
    from controllers.dynamics import jacobians

    fx, A, B = jacobians(system, x, u_bar)
    c = fx - (A @ x.unsqueeze(-1)).squeeze(-1) - (B @ u_bar.unsqueeze(-1)).squeeze(-1)
    u, _ = lq_first_action(A, B, c, Q, R, x_ref, u_ref, x, horizon)
    if lower is not None:
        u = torch.maximum(u, lower)
    if upper is not None:
        u = torch.minimum(u, upper)
    return u
