"""Manifolds as batched, differentiable functions on plain tensors: one class per space, two vocabularies.

Where each space lives
----------------------

==============  ================================================  ==========  ============
file            contents                                          ⊞/⊟/⊕, G    Exp/Log
==============  ================================================  ==========  ============
``base.py``     :class:`Manifold` (the contract), the                —           —
                :class:`RiemannianManifold` protocol,
                :func:`manifold_tolerance`, shared helpers
``groups.py``   :class:`Rn` (= ``Euclidean``), :class:`SO2`,        yes         yes
                :class:`SO3`, :class:`SE3`
``sphere.py``   :class:`Sphere` (Sᵈ of radius r; ``S2(r)`` =        S² only     yes
                ``Sphere(2, r)``), ``sphere_exp/log/dist/
                transport/transport_matrix``, ``hemisphere_align``
``surface.py``  :class:`Surface`, :func:`quadratic_surface`,        yes         no
                :func:`fit_quadratic_surface`, :class:`SurfaceFit`
``spd.py``      :class:`SPD`, :class:`SPDTransport`, ``spd_exp/     no          yes
                log/dist/transport(_geodesic)/to_coords/
                from_coords``, ``sym_sqrtm/invsqrtm/logm/expm``
``product.py``  :class:`ProductManifold`, :class:`ProductState`     yes         no
``statistics.py`` :func:`karcher_mean`, :func:`tangent_covariance`,   —           uses it
                :func:`fit_gaussian`, :func:`gaussian_log_density`,
                :func:`gaussian_product` (any space with Exp/Log)
``metric.py``   :func:`geodesic`, :func:`path_energy`,              —           —
                :func:`path_length` under a varying metric ``G(x)``
                (non-homogeneous manifolds, seed 004 §12.6)
==============  ================================================  ==========  ============

Two vocabularies on one class
-----------------------------

* **⊞ / ⊟ / ⊕ with G_x, G_f** (seed 003, on-manifold MPC): ``boxplus(x, δ)``, ``boxminus(y, x)``,
  ``oplus(x, δᵉ)``, ``G_x``/``G_f`` of Table I (exact derivatives of Eq. 23; ``exact=True`` for
  autograd), ``linearize``.  δ lives in chart coordinates Rⁿ, n = ``dim``.
* **Exp / Log at a point** (seed 004 §12, Riemannian statistics): ``exp_at(x, v)``, ``log_at(x, y)``,
  ``dist``, ``transport_matrix``/``transport``, ``normal_basis``; v lives in an orthonormal frame
  of the metric, ``(*, tangent_size)``:

  ===========  ==================  =========  ======================================================
  space        point shape         m          tangent representation of exp_at / log_at
  ===========  ==================  =========  ======================================================
  Rn(n)        ``(n,)``            n          x + v, y − x (= ⊞, ⊟)
  SO2()        ``(2, 2)``          1          body-frame θ: X exp(θ), log(XᵀY) (= ⊞, ⊟)
  SO3()        ``(3, 3)``          3          body-frame ω: X exp(ω), log(XᵀY) (= ⊞, ⊟)
  SE3()        ``(4, 4)``          6          body-frame [ρ, ω]: X exp(ξ), log(X⁻¹Y) (= ⊞, ⊟)
  Sphere(d,r)  ``(d+1,)``          d+1        ambient vector ⟂ x (rank d; the normal is x/r);
                                              ⊟ of S² gives instead 2-vectors in the basis B(x)
  SPD(n)       ``(n, n)``          n(n+1)/2   Mandel vector of X^{-1/2} U X^{-1/2} (whitened)
  ===========  ==================  =========  ======================================================

  Where the two vocabularies are the same map the class has one implementation; where they are
  different maps (the sphere) both are kept with their documented coordinates, and the tests check
  how they relate.  ``has_boxplus`` and ``has_exp_log`` tell which a space has.

One tolerance rule
------------------

Every membership check (points, tangent vectors, symmetric matrices; both vocabularies and the
functional cores) compares with :func:`manifold_tolerance`, ``sqrt(eps)`` of the dtype (float64
1.5e-8, float32 3.5e-4); its docstring says why this rule.  Off-manifold inputs raise
``ValueError`` naming the argument and the first bad batch index, or are projected with
``project=True``; ``check=False`` is the explicit "already checked" switch (solver loops, vmap).

Points are plain tensors (``ProductState`` for products); every function accepts any leading batch
dims, broadcasts, keeps dtype and device, and is differentiable.
"""

from torchlie.manifolds.base import Manifold, RiemannianManifold, manifold_tolerance
from torchlie.manifolds.groups import SE3, SO2, SO3, Euclidean, Rn
from torchlie.manifolds.metric import Geodesic, GeodesicReason, geodesic, path_energy, path_length
from torchlie.manifolds.product import ProductManifold, ProductState
from torchlie.manifolds.spd import (
    SPD,
    SPDTransport,
    spd_dist,
    spd_exp,
    spd_from_coords,
    spd_log,
    spd_to_coords,
    spd_transport,
    spd_transport_geodesic,
    sym_expm,
    sym_invsqrtm,
    sym_logm,
    sym_sqrtm,
)
from torchlie.manifolds.sphere import (
    S2,
    Sphere,
    hemisphere_align,
    sphere_dist,
    sphere_exp,
    sphere_log,
    sphere_transport,
    sphere_transport_matrix,
)
from torchlie.manifolds.statistics import (
    KarcherMean,
    ManifoldGaussian,
    fit_gaussian,
    gaussian_log_density,
    gaussian_product,
    karcher_mean,
    tangent_covariance,
)
from torchlie.manifolds.surface import Surface, SurfaceFit, fit_quadratic_surface, quadratic_surface

__all__ = [
    # the contract and the tolerance (base.py)
    "Manifold",
    "RiemannianManifold",
    "manifold_tolerance",
    # Euclidean space and Lie groups (groups.py)
    "Rn",
    "Euclidean",
    "SO2",
    "SO3",
    "SE3",
    # spheres (sphere.py)
    "Sphere",
    "S2",
    "sphere_exp",
    "sphere_log",
    "sphere_dist",
    "sphere_transport",
    "sphere_transport_matrix",
    "hemisphere_align",
    # height surfaces (surface.py)
    "Surface",
    "SurfaceFit",
    "quadratic_surface",
    "fit_quadratic_surface",
    # SPD matrices (spd.py)
    "SPD",
    "SPDTransport",
    "sym_sqrtm",
    "sym_invsqrtm",
    "sym_logm",
    "sym_expm",
    "spd_exp",
    "spd_log",
    "spd_dist",
    "spd_transport",
    "spd_transport_geodesic",
    "spd_to_coords",
    "spd_from_coords",
    # products (product.py)
    "ProductManifold",
    "ProductState",
    # statistics (statistics.py)
    "KarcherMean",
    "ManifoldGaussian",
    "karcher_mean",
    "tangent_covariance",
    "fit_gaussian",
    "gaussian_log_density",
    "gaussian_product",
    # varying metrics (metric.py)
    "Geodesic",
    "GeodesicReason",
    "geodesic",
    "path_energy",
    "path_length",
]
