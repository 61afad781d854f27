"""controllers: batched, differentiable LQT/LQR/iLQR/MPC on plain tensors.

Submodules (loaded on first use, ``controllers.riccati``):

=============  =====================================================================================
``dynamics``   the ``System`` protocol, linear/nonlinear dynamics, rollout, Jacobians, linearization
``costs``      the ``Cost`` protocol and the one cost convention; quadratic/residual costs, derivatives,
               cost modules for ``MPCPolicy``
``problem``    LQ problems and solutions, per-element status (``Reason``), ``GradMode``
``lifted``     batch least-squares LQT with transfer matrices S_x, S_u (seed 004 §7, Eq. 61-65), oracle
``lqt_cookbook`` §7's LQT variants: nullspace LQT, DMP as LQT with primitives, agents meeting, tennis serve
``riccati``    recursive Riccati LQR/LQT with feedback gains (§7.4-7.6); ``prepare`` for re-solves
``implicit``   implicit (KKT) gradients of the LQ solution and of iLQR's
``basis``      piecewise, RBF, Bernstein and Fourier basis functions, their derivatives, splines with a
               continuity matrix and multi-dimensional (tensor-product) bases (§6)
``sdf``        signed distance fields on basis functions: eikonal Gauss-Newton fit, closest points (§6.8)
``ilqr``       iLQR (batch and recursive) with control limits (§8)
``ilqr_lifted`` batch iLQR (Algorithm 4) in ``[x0; w]`` with ``u = Ψ w``: control primitives (§9.12),
               initial-state optimization (§9.4), least-squares feedback gains (§8.3)
``task_costs_ext`` §9.10-9.14: decoupled controls, curvature, spacetime (phase) dynamics,
               affordance offsets coupled across time, sums of costs
``task_costs`` the §9 cost zoo as residuals with Jacobians: tracking, joint/task/object bounds, CoM,
               ellipsoid obstacles, distances, composed into one ``ResidualCost``
``boxqp``      batched box-constrained QP (projected Newton)
``mpc``        receding-horizon MPC, ``MPCState`` and the ``MPCPolicy`` module
``multistart`` iLQR from K initial guesses at once (zero, bang, random, the closed-loop LQR "hold"), the
               best certified plan kept
``sampling``   MPPI and predictive sampling, batched and derivative-free; ``SamplingMPC``
``linear_mpc`` linear MPC about the current state: one linearization, one Riccati recursion, first control
``manifold_mpc`` error-state MPC on ``torchlie`` manifolds (seed 003 Algorithm 1 and its iterated variant)
``ik``         damped least squares and batched IK
``planar_ik``  planar arms (§4-5): FK/Jacobians, Gauss-Newton IK (position, orientation, object frame),
               task-priority IK with null-space projectors
``impedance``  joint- and task-space impedance control with gravity compensation, simulated (§11)
``optim``      gradient descent, Newton, Gauss-Newton with backtracking; ridge/weighted/constrained least
               squares (§3), batched with certified statuses
``ergodic``    ergodic control (§10): SMC (myopic and planned) and HEDAC, several agents
``systems``    system models
=============  =====================================================================================

Private: ``_validate`` (argument checks), ``_lq_kernels`` (the Riccati sweeps shared by ``riccati`` and
``implicit``).  Imports flow ``mpc → ilqr → implicit → _lq_kernels`` and ``riccati → implicit``, with
``dynamics``/``costs``/``problem`` below every solver.
"""

import importlib

__all__ = ["dynamics", "costs", "problem", "lifted", "riccati", "implicit", "basis", "sdf", "ilqr",
           "ilqr_lifted", "task_costs", "task_costs_ext", "lqt_cookbook", "boxqp", "mpc", "multistart",
           "sampling", "linear_mpc", "manifold_mpc", "ik", "planar_ik", "impedance", "optim", "ergodic",
           "systems"]


def __getattr__(name: str):
    if name in __all__:
        return importlib.import_module(f"controllers.{name}")
    raise AttributeError(f"module 'controllers' has no attribute {name!r}")
