"""controllers: batched, differentiable LQT/LQR/iLQR/MPC on plain tensors.

Submodules (loaded on first use, ``controllers.riccati``):

=============  =====================================================================================
``problem``    frozen dataclasses: dynamics, quadratic costs, LQ problems, solutions with per-element status
``lifted``     batch least-squares LQT with transfer matrices S_x, S_u (seed 004 §7, Eq. 61-65), oracle
``riccati``    recursive Riccati LQR/LQT with feedback gains (§7.4-7.6)
``implicit``   implicit (KKT / backward Riccati) gradients of the LQ solution
``basis``      piecewise, RBF, Bernstein and Fourier basis functions (§6)
``linearize``  Jacobians of batched nonlinear dynamics along a trajectory (torch.func or analytic)
``ilqr``       iLQR (batch and recursive) with control limits (§8)
``boxqp``      batched box-constrained QP (projected Newton)
``mpc``        receding-horizon MPC and the ``MPCPolicy`` module
``systems``    system models
=============  =====================================================================================
"""

import importlib

__all__ = ["problem", "lifted", "riccati", "implicit", "basis", "linearize",
           "ilqr", "boxqp", "mpc", "systems"]


def __getattr__(name: str):
    if name in __all__:
        return importlib.import_module(f"controllers.{name}")
    raise AttributeError(f"module 'controllers' has no attribute {name!r}")
