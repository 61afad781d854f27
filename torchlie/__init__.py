"""torchlie: Lie groups and manifolds as exact, batched, differentiable functions on plain tensors.

Group modules (``so2``, ``se2``, ``so3``, ``se3``) share one functional contract, written once here:

=====================  ===================================================================
``exp(x)``             tangent ``(*, d)`` -> group matrix ``(*, n, n)``
``log(X)``             group matrix -> principal tangent vector (rotation angle in [0, π])
``hat(x)``/``vee(M)``  tangent vector <-> Lie-algebra matrix
``compose(X, Y)``      ``X @ Y`` with broadcasting over leading dims
``inverse(X)``         closed-form inverse
``act(X, p)``          ``X`` applied to points ``(*, k)`` (k = 2 or 3)
``adjoint(X)``         Ad_X ``(*, d, d)`` with ``X exp(x) X⁻¹ = exp(Ad_X x)``
``ad(x)``              ad_x ``(*, d, d)`` with ``ad_x y = [x, y]`` (seed 000 Eq. 3-4 for so(3)/se(3))
``left_jacobian(x)``   J_l with ``exp(x + δ) ≈ exp(J_l δ) exp(x)``  (Solà et al., *A micro Lie theory*)
``right_jacobian(x)``  J_r with ``exp(x + δ) ≈ exp(x) exp(J_r δ)``; ``*_inv`` are the inverses
``identity(*batch)``   identity element; ``random(*batch, generator=)`` uniform (Haar) sample
``interpolate(X,Y,t)`` geodesic ``X exp(t log(X⁻¹ Y))``
=====================  ===================================================================

Conventions: SO(2)/SO(3) are rotation matrices, SE(2)/SE(3) homogeneous matrices; the se(3) tangent
is ``[v, ω]`` (seed 000 Eq. 2), se(2) is ``[vx, vy, θ]``; quaternions are ``(w, x, y, z)``.
Every function accepts any number of leading batch dims, broadcasts binary operations, keeps dtype
and device, and has finite gradients everywhere including at the identity and at angle π.

The package ``manifolds`` builds on these modules: one class per space (Rⁿ, SO(2), SO(3), SE(3),
spheres, height surfaces, SPD matrices, products) carrying both the ⊞/⊟/⊕ vocabulary of on-manifold
MPC and the Exp/Log/transport vocabulary of Riemannian statistics (Karcher mean, Gaussians); its
``__init__`` maps which file holds which space.  ``magnus`` holds dexp⁻¹ and the ME2 predictor.
"""

import importlib

__all__ = ["so2", "se2", "so3", "se3", "quaternion", "manifolds", "magnus"]


def __getattr__(name: str):
    # Submodules load on first use (``torchlie.so3``) so importing torchlie stays cheap.
    if name in __all__:
        return importlib.import_module(f"torchlie.{name}")
    raise AttributeError(f"module 'torchlie' has no attribute {name!r}")
