"""Products of manifolds (seed 003 Eq. 13, 33, 36): :class:`ProductManifold` and its points,
:class:`ProductState`.

``ProductManifold({"p": Rn(3), "v": Rn(3), "R": SO3()})`` is the quadrotor state space of Eq. 33;
tangent vectors and exogenous perturbations are the components' vectors concatenated in component
order, and ``G_x``/``G_f`` are block diagonal (Eq. 13).  A product has the ⊞ vocabulary (every
component must have it); it has no Exp/Log of its own.

Product states (:class:`ProductState`).  A product point is an immutable mapping of component
names to tensors (``x.p``, ``x.v``, ``x.R``), registered as a pytree node, with
tensor-like batch methods (indexing, ``reshape``, ``expand``, ``unsqueeze``, ``to``, ``detach``,
``stack``/``cat``).  Why this and not the alternatives: a frozen dataclass needs one class per
product (the component names are chosen by the user at run time, so the classes would have to be
generated dynamically, and each registered as a pytree and made picklable); a tensordict is an
extra heavy dependency with mutable semantics and its own batch-size bookkeeping, and it reaches
``torch.func`` through its own functional API.  The small pytree-registered mapping gives attribute
access by name, works directly with ``torch.func.vmap/jacrev/grad`` and torch's pytree
utilities, keeps autograd untouched (its leaves are ordinary tensors) and costs no dependency.
Each leaf records how many trailing dims are the point itself (1 for vectors, 2 for matrices),
so batch operations know which dims are batch dims.

The pytree registry is reached through ``torch.utils._pytree``, imported in this module only:
torch 2.13 has no public pytree module (``torch.utils.pytree`` does not exist, ``torch.export.pytree``
is only that private module imported under another name, ``torch.export.register_dataclass``
registers dataclasses only, and ``torch.func`` exposes no registry), while
``torch.func`` transforms flatten their inputs with exactly this registry.  If a public module
appears, change the one import below.
"""

from __future__ import annotations

import dataclasses
import keyword
import types
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import torch

# The one private torch import of torchlie.manifolds (no public pytree API exists; see the module
# docstring).  Used for: register_pytree_node, GetAttrKey, tree_leaves.
from torch.utils import _pytree as pytree

from torchlie._batch import broadcast_shapes, check_tensor
from torchlie.manifolds.base import Manifold, _expand_to

__all__ = ["ProductManifold", "ProductState"]


# ------------------------------------------------------------------------------------------------
# product states
# ------------------------------------------------------------------------------------------------

_Leaf = Any  # torch.Tensor or ProductState (or, inside torch.func internals, any pytree leaf)


class ProductState:
    """A point of a :class:`ProductManifold`: named components, batched like a tensor.

    ``x.R`` / ``x["R"]`` give a component; ``x[0]``, ``x[:, 1]``, ``x[mask]`` index the *batch*
    dims of every component; ``reshape``, ``expand``, ``unsqueeze``, ``to``, ``detach``, ``clone``,
    ``requires_grad_`` act on all components; ``replace(R=...)`` returns a copy with some
    components swapped; ``ProductState.stack``/``cat`` join states along a batch dim.
    Immutable, and registered as a pytree node (see the module docstring for why), so
    ``torch.func.vmap``/``jacrev``/``grad`` and ``torch.utils._pytree.tree_map`` accept it.

    Built by :meth:`ProductManifold.state` (which checks the points); the constructor takes the
    components and, per tensor component, the number of trailing dims that are the point itself
    (``event_ndims``), and broadcasts the components' batch dims to one batch shape.
    """

    __slots__ = ("_data", "_event_ndims")

    def __init__(self, components: Mapping[str, _Leaf], event_ndims: Mapping[str, int]):
        if not isinstance(components, Mapping) or not components:
            raise TypeError("ProductState: argument 'components' must be a non-empty mapping name -> tensor")
        data: dict[str, _Leaf] = {}
        nd: dict[str, int] = {}
        for name, t in components.items():
            _check_component_name(name, "ProductState")
            if isinstance(t, ProductState):
                data[name] = t
                continue
            if not isinstance(t, torch.Tensor):
                raise TypeError(f"ProductState: component '{name}' must be a tensor or ProductState, "
                                f"got {type(t).__name__}")
            k = event_ndims.get(name) if isinstance(event_ndims, Mapping) else None
            if not isinstance(k, int) or k < 0 or t.dim() < k:
                raise ValueError(f"ProductState: 'event_ndims' must give the point dims (≤ {t.dim()}) "
                                 f"of component '{name}', got {k!r}")
            data[name], nd[name] = t, k
        shapes = [_leaf_batch(t, nd.get(n)) for n, t in data.items()]
        try:
            batch = broadcast_shapes(*shapes)
        except RuntimeError as e:
            raise ValueError("ProductState: the components' batch shapes do not broadcast: "
                             + ", ".join(f"'{n}' {tuple(s)}" for n, s in zip(data, shapes))) from e
        data = {n: _leaf_expand(t, nd.get(n), batch) for n, t in data.items()}
        object.__setattr__(self, "_data", data)
        object.__setattr__(self, "_event_ndims", nd)

    @classmethod
    def _make(cls, data: Mapping[str, _Leaf], event_ndims: Mapping[str, int]) -> ProductState:
        obj = object.__new__(cls)
        object.__setattr__(obj, "_data", dict(data))
        object.__setattr__(obj, "_event_ndims", dict(event_ndims))
        return obj

    def __reduce__(self):
        return (ProductState._make, (self._data, self._event_ndims))

    # --- access -----------------------------------------------------------------------------------
    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)
        try:
            return self._data[name]
        except KeyError:
            raise AttributeError(f"ProductState has no component {name!r}; components: "
                                 f"{list(self._data)}") from None

    def __setattr__(self, name, value):
        raise AttributeError("ProductState is immutable; use x.replace(name=value)")

    def keys(self):
        return self._data.keys()

    def values(self):
        return self._data.values()

    def items(self):
        return self._data.items()

    def __contains__(self, name) -> bool:
        return name in self._data

    def to_dict(self) -> dict[str, _Leaf]:
        return dict(self._data)

    @property
    def event_ndims(self) -> Mapping[str, int]:
        return types.MappingProxyType(self._event_ndims)

    def replace(self, **components: _Leaf) -> ProductState:
        """Copy with some components replaced (batch shapes broadcast again)."""
        unknown = set(components) - set(self._data)
        if unknown:
            raise ValueError(f"ProductState.replace: unknown components {sorted(unknown)}; "
                             f"components: {list(self._data)}")
        return ProductState({**self._data, **components}, self._event_ndims)

    # --- tensor-like properties -------------------------------------------------------------------
    def _first_leaf(self):
        t = next(iter(self._data.values()))
        return t._first_leaf() if isinstance(t, ProductState) else t

    @property
    def batch_shape(self) -> torch.Size:
        name, t = next(iter(self._data.items()))
        return _leaf_batch(t, self._event_ndims.get(name))

    @property
    def shape(self) -> torch.Size:
        """Alias of ``batch_shape`` (the shape that indexing and reshape act on)."""
        return self.batch_shape

    @property
    def ndim(self) -> int:
        return len(self.batch_shape)

    @property
    def dtype(self) -> torch.dtype:
        return self._first_leaf().dtype

    @property
    def device(self) -> torch.device:
        return self._first_leaf().device

    @property
    def requires_grad(self) -> bool:
        return any(t.requires_grad for t in pytree.tree_leaves(self) if isinstance(t, torch.Tensor))

    def __len__(self) -> int:
        b = self.batch_shape
        if not b:
            raise TypeError("len() of a ProductState with no batch dims")
        return b[0]

    # --- batch operations -------------------------------------------------------------------------
    def _map(self, f: Callable[[torch.Tensor, int], torch.Tensor]) -> ProductState:
        out = {}
        for name, t in self._data.items():
            out[name] = t._map(f) if isinstance(t, ProductState) else f(t, self._event_ndims[name])
        return ProductState._make(out, self._event_ndims)

    def __getitem__(self, key):
        if isinstance(key, str):
            try:
                return self._data[key]
            except KeyError:
                raise KeyError(f"ProductState has no component {key!r}; "
                               f"components: {list(self._data)}") from None
        idx = key if isinstance(key, tuple) else (key,)
        nb = self.ndim
        if any(i is Ellipsis for i in idx):
            if sum(i is Ellipsis for i in idx) > 1:
                raise IndexError("ProductState: an index can only have a single ellipsis ('...')")
            used = sum(_index_consumes(i) for i in idx if i is not Ellipsis)
            pos = next(j for j, i in enumerate(idx) if i is Ellipsis)
            idx = idx[:pos] + (slice(None),) * max(nb - used, 0) + idx[pos + 1:]
        if sum(_index_consumes(i) for i in idx) > nb:
            raise IndexError(f"ProductState: too many indices for batch shape {tuple(self.batch_shape)} "
                             "(indexing acts on the batch dims only; use x.name for a component)")
        return self._map(lambda t, k: t[idx])

    def reshape(self, *shape) -> ProductState:
        """Reshape the batch dims (the point dims are kept)."""
        shape = _shape_arg(shape)
        return self._map(lambda t, k: t.reshape(*shape, *t.shape[t.dim() - k:]))

    def view(self, *shape) -> ProductState:
        shape = _shape_arg(shape)
        return self._map(lambda t, k: t.view(*shape, *t.shape[t.dim() - k:]))

    def flatten(self) -> ProductState:
        """All batch dims flattened into one."""
        return self.reshape(-1)

    def expand(self, *shape) -> ProductState:
        shape = _shape_arg(shape)
        return self._map(lambda t, k: t.expand(*shape, *t.shape[t.dim() - k:]))

    def unsqueeze(self, dim: int) -> ProductState:
        """Insert a batch dim at ``dim`` (negative counts from the end of the batch dims)."""
        nb = self.ndim
        d = dim if dim >= 0 else dim + nb + 1
        if not 0 <= d <= nb:
            raise IndexError(f"ProductState.unsqueeze: dim {dim} out of range for {nb} batch dims")
        return self._map(lambda t, k: t.unsqueeze(d))

    def squeeze(self, dim: int) -> ProductState:
        nb = self.ndim
        d = dim if dim >= 0 else dim + nb
        if not 0 <= d < nb:
            raise IndexError(f"ProductState.squeeze: dim {dim} out of range for {nb} batch dims")
        return self._map(lambda t, k: t.squeeze(d))

    def to(self, *args, **kwargs) -> ProductState:
        """``Tensor.to`` on every component (device and/or dtype)."""
        return self._map(lambda t, k: t.to(*args, **kwargs))

    def detach(self) -> ProductState:
        return self._map(lambda t, k: t.detach())

    def clone(self) -> ProductState:
        return self._map(lambda t, k: t.clone())

    def contiguous(self) -> ProductState:
        return self._map(lambda t, k: t.contiguous())

    def requires_grad_(self, requires_grad: bool = True) -> ProductState:
        for t in pytree.tree_leaves(self):
            t.requires_grad_(requires_grad)
        return self

    @staticmethod
    def stack(states: Iterable[ProductState], dim: int = 0) -> ProductState:
        """Stack states of equal batch shape along a new batch dim."""
        states = list(states)
        if not states:
            raise ValueError("ProductState.stack: argument 'states' is empty")
        nb = states[0].ndim
        d = dim if dim >= 0 else dim + nb + 1
        return _zip_map(states, lambda ts, k: torch.stack(ts, d))

    @staticmethod
    def cat(states: Iterable[ProductState], dim: int = 0) -> ProductState:
        """Concatenate states along an existing batch dim."""
        states = list(states)
        if not states:
            raise ValueError("ProductState.cat: argument 'states' is empty")
        nb = states[0].ndim
        d = dim if dim >= 0 else dim + nb
        return _zip_map(states, lambda ts, k: torch.cat(ts, d))

    def __repr__(self) -> str:
        parts = []
        for name, t in self._data.items():
            if isinstance(t, ProductState):
                parts.append(f"{name}={t!r}")
            elif isinstance(t, torch.Tensor):
                parts.append(f"{name}: {tuple(t.shape)} {str(t.dtype).replace('torch.', '')}")
            else:
                parts.append(f"{name}: {type(t).__name__}")
        try:
            b = f", batch_shape={tuple(self.batch_shape)}"
        except Exception:  # leaves that are not tensors (inside torch.func internals)
            b = ""
        return f"ProductState({', '.join(parts)}{b})"


def _leaf_batch(t, k) -> torch.Size:
    if isinstance(t, ProductState):
        return t.batch_shape
    return t.shape[: t.dim() - k]


def _leaf_expand(t, k, batch):
    if isinstance(t, ProductState):
        return t if t.batch_shape == batch else t.expand(*batch)
    return _expand_to(t, k, batch)


def _shape_arg(shape) -> tuple[int, ...]:
    if len(shape) == 1 and isinstance(shape[0], (tuple, list, torch.Size)):
        return tuple(shape[0])
    return tuple(shape)


def _index_consumes(i) -> int:
    if i is None:
        return 0
    if isinstance(i, torch.Tensor) and i.dtype == torch.bool:
        return i.dim()
    return 1


def _zip_map(states: list[ProductState], f) -> ProductState:
    first = states[0]
    for s in states[1:]:
        if not isinstance(s, ProductState) or list(s.keys()) != list(first.keys()):
            raise ValueError("ProductState: all states must have the same components in the same order")
    out = {}
    for name, t in first.items():
        comps = [s[name] for s in states]
        out[name] = _zip_map(comps, f) if isinstance(t, ProductState) else f(comps, first._event_ndims[name])
    return ProductState._make(out, first._event_ndims)


_RESERVED = {n for n in dir(ProductState) if not n.startswith("_")} | {"project"}


def _check_component_name(name, where: str) -> None:
    ok = isinstance(name, str) and name.isidentifier() and not keyword.iskeyword(name)
    if not ok or name.startswith("_"):
        raise ValueError(f"{where}: component name {name!r} must be a Python identifier not starting "
                         "with '_'")
    if name in _RESERVED:
        raise ValueError(f"{where}: component name {name!r} is reserved (a ProductState method or "
                         "attribute has that name)")


def _ps_flatten(s: ProductState):
    return list(s._data.values()), (tuple(s._data.keys()), tuple(sorted(s._event_ndims.items())))


def _ps_unflatten(values, context) -> ProductState:
    names, nd = context
    return ProductState._make(dict(zip(names, values)), dict(nd))


def _ps_flatten_with_keys(s: ProductState):
    return [(pytree.GetAttrKey(n), t) for n, t in s._data.items()], _ps_flatten(s)[1]


pytree.register_pytree_node(
    ProductState,
    _ps_flatten,
    _ps_unflatten,
    serialized_type_name="torchlie.manifolds.ProductState",
    flatten_with_keys_fn=_ps_flatten_with_keys,
)


# ------------------------------------------------------------------------------------------------
# product manifold
# ------------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True, eq=True)
class ProductManifold(Manifold):
    """Cartesian product 𝓜₁ × … × 𝓜ₖ with named components (Eq. 13).

    ``ProductManifold({"p": Rn(3), "v": Rn(3), "R": SO3()})`` is the quadrotor state space of
    Eq. 33 (n = 9, l = 9); ``ProductManifold({"s": Surface(F, gF, hF), "R": SO2()})`` the ground
    vehicle of Eq. 36 (n = 3, l = 3).  Points are :class:`ProductState`; tangent vectors δ ``(*, n)``
    and exogenous perturbations δᵉ ``(*, l)`` are the components' vectors concatenated in
    component order (``slices``/``ext_slices`` give the ranges); ``G_x``/``G_f`` are block
    diagonal.  Components may themselves be products.
    """

    components: Mapping[str, Manifold]

    def __post_init__(self):
        comps = self.components
        if not isinstance(comps, Mapping) or not comps:
            raise TypeError("ProductManifold: argument 'components' must be a non-empty mapping "
                            "name -> Manifold")
        for name, m in comps.items():
            _check_component_name(name, "ProductManifold")
            if not isinstance(m, Manifold):
                raise TypeError(f"ProductManifold: component '{name}' must be a Manifold, "
                                f"got {type(m).__name__}")
            if not m.has_boxplus:
                raise TypeError(f"ProductManifold: component '{name}' ({m!r}) has no ⊞/⊟/⊕ (seed 003), "
                                "which a product needs")
        object.__setattr__(self, "components", types.MappingProxyType(dict(comps)))

    def __hash__(self):
        return hash(tuple(self.components.items()))

    def __eq__(self, other):
        return isinstance(other, ProductManifold) and tuple(self.components.items()) == tuple(
            other.components.items())

    def __repr__(self):
        return "ProductManifold(" + ", ".join(f"{n}={m!r}" for n, m in self.components.items()) + ")"

    @property
    def dim(self) -> int:
        return sum(m.dim for m in self.components.values())

    @property
    def ext_dim(self) -> int:
        return sum(m.ext_dim for m in self.components.values())

    @property
    def event_shape(self) -> tuple[int, ...]:
        raise AttributeError("a ProductManifold point is a ProductState, not one tensor")

    def _ranges(self, attr: str) -> dict[str, slice]:
        out, i = {}, 0
        for name, m in self.components.items():
            d = getattr(m, attr)
            out[name] = slice(i, i + d)
            i += d
        return out

    @property
    def slices(self) -> Mapping[str, slice]:
        """Range of each component in a tangent vector δ ``(*, n)``."""
        return types.MappingProxyType(self._ranges("dim"))

    @property
    def ext_slices(self) -> Mapping[str, slice]:
        """Range of each component in an exogenous perturbation δᵉ ``(*, l)``."""
        return types.MappingProxyType(self._ranges("ext_dim"))

    def _event_ndims(self) -> dict[str, int]:
        return {n: len(m.event_shape) for n, m in self.components.items()
                if not isinstance(m, ProductManifold)}

    def _batch_shape(self, x) -> torch.Size:
        return x.batch_shape

    def _leaf(self, x) -> torch.Tensor:
        return x._first_leaf()

    def _describe(self) -> str:
        return repr(self)

    def _check_point(self, x, name: str, fn: str, project: bool, check: bool = True):
        if not isinstance(x, ProductState):
            raise TypeError(f"{fn}: argument '{name}' must be a ProductState with components "
                            f"{list(self.components)} (build one with manifold.state(...)), "
                            f"got {type(x).__name__}")
        if list(x.keys()) != list(self.components):
            raise ValueError(f"{fn}: argument '{name}' has components {list(x.keys())}, expected "
                             f"{list(self.components)}")
        out = {}
        dev = None
        for cname, m in self.components.items():
            t = m._check_point(x[cname], f"{name}.{cname}", fn, project, check)
            leaf = t._first_leaf() if isinstance(t, ProductState) else t
            if dev is None:
                dev, dt, first = leaf.device, leaf.dtype, cname
            elif leaf.device != dev or leaf.dtype != dt:
                raise ValueError(f"{fn}: components '{name}.{first}' and '{name}.{cname}' differ in "
                                 f"device or dtype ({dev}, {dt} vs {leaf.device}, {leaf.dtype})")
            out[cname] = t
        if all(out[c] is x[c] for c in out):
            return x  # nothing projected: the checked state itself (no rebuild)
        return ProductState(out, self._event_ndims())

    def state(self, *, project: bool = False, **components) -> ProductState:
        """Build a checked :class:`ProductState`, e.g. ``M.state(p=p, v=v, R=R)``."""
        missing = [n for n in self.components if n not in components]
        extra = [n for n in components if n not in self.components]
        if missing or extra:
            raise ValueError(f"ProductManifold.state: expected components {list(self.components)}; "
                             f"missing {missing}, unexpected {extra}")
        for cname, t in components.items():
            m = self.components[cname]
            if not isinstance(m, ProductManifold):
                check_tensor(t, m.event_shape, cname, "ProductManifold.state")
        raw = ProductState({n: components[n] for n in self.components}, self._event_ndims())
        return self._check_point(raw, "x", "ProductManifold.state", project)

    def _split(self, d: torch.Tensor, attr: str) -> dict[str, torch.Tensor]:
        return {n: d[..., sl] for n, sl in self._ranges(attr).items()}

    def _boxplus(self, x, delta):
        parts = self._split(delta, "dim")
        return ProductState({n: m._boxplus(x[n], parts[n]) for n, m in self.components.items()},
                            self._event_ndims())

    def _boxminus(self, y, x):
        outs = [m._boxminus(y[n], x[n]) for n, m in self.components.items()]
        batch = broadcast_shapes(*(o.shape[:-1] for o in outs))
        return torch.cat([o.expand(*batch, o.shape[-1]) for o in outs], -1)

    def _oplus(self, x, delta_e):
        parts = self._split(delta_e, "ext_dim")
        return ProductState({n: m._oplus(x[n], parts[n]) for n, m in self.components.items()},
                            self._event_ndims())

    def _block_diag(self, blocks: list[torch.Tensor], cols: list[int]) -> torch.Tensor:
        batch = broadcast_shapes(*(b.shape[:-2] for b in blocks))
        total = sum(cols)
        rows, start = [], 0
        for b, c in zip(blocks, cols):
            b = b.expand(*batch, *b.shape[-2:])
            r = b.shape[-2]
            left = b.new_zeros(*batch, r, start)
            right = b.new_zeros(*batch, r, total - start - c)
            rows.append(torch.cat((left, b, right), -1))
            start += c
        return torch.cat(rows, -2)

    def _G_x(self, x_d, v):
        parts = self._split(v, "ext_dim")
        blocks = [m._G_x(x_d[n], parts[n]) for n, m in self.components.items()]
        return self._block_diag(blocks, [m.dim for m in self.components.values()])

    def _G_f(self, x_d, v):
        parts = self._split(v, "ext_dim")
        blocks = [m._G_f(x_d[n], parts[n]) for n, m in self.components.items()]
        return self._block_diag(blocks, [m.ext_dim for m in self.components.values()])

    def _linearize(self, x_d, v, dt, df_dx, df_du):
        """Eq. 21-22 by row blocks: component i contributes ``G_x,i`` on its own columns plus
        ``Δt G_f,i (∂f/∂δx)_i``; identity G's (Rⁿ, SO(2), surfaces) skip their products."""
        n = self.dim
        batch = broadcast_shapes(self._batch_shape(x_d), v.shape[:-1], df_dx.shape[:-2],
                                       df_du.shape[:-2])
        parts = self._split(v, "ext_dim")
        eye = torch.eye(n, dtype=v.dtype, device=v.device)
        rows_x, rows_u = [], []
        comps = zip(self.components.items(), self.slices.values(), self.ext_slices.values())
        for (name, m), sl, esl in comps:
            Jx, Ju = df_dx[..., esl, :], df_du[..., esl, :]
            if m._G_identity:
                rows_x.append(eye[sl] + dt * Jx)
                rows_u.append(dt * Ju)
                continue
            Gx, Gf = m._G_x(x_d[name], parts[name]), m._G_f(x_d[name], parts[name])
            left = Gx.new_zeros(*Gx.shape[:-1], sl.start)
            right = Gx.new_zeros(*Gx.shape[:-1], n - sl.stop)
            rows_x.append(torch.cat([left, Gx, right], -1) + dt * (Gf @ Jx))
            rows_u.append(dt * (Gf @ Ju))
        A = torch.cat([r.expand(*batch, *r.shape[-2:]) for r in rows_x], -2)
        B = torch.cat([r.expand(*batch, *r.shape[-2:]) for r in rows_u], -2)
        return A, B

    def _random(self, batch, generator, dtype, device):
        comps = self.components.items()
        return ProductState({n: m._random(batch, generator, dtype, device) for n, m in comps},
                            self._event_ndims())

    def _identity(self, batch, dtype, device):
        return ProductState({n: m._identity(batch, dtype, device) for n, m in self.components.items()},
                            self._event_ndims())
