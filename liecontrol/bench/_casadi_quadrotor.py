"""Anchor for the quadrotor error-state MPC: the same nonlinear MPC written with CasADi + IPOPT.

This is what a user would otherwise write: a multiple-shooting NLP of the same discrete model, horizon,
weights and input box, built once with ``casadi.nlpsol`` (IPOPT, exact Hessian) and re-solved at every
step with the current state and the reference window passed as parameters.  casadi is imported lazily
(inside functions), so importing this module does not need it.

Model (NED, z down; ``e3 = (0, 0, 1)``), state ``x = (p, v, R)``, control ``u = (a_T, ω_x, ω_y, ω_z)``::

    p⁺ = p + dt v
    v⁺ = v + dt (g e3 − a_T R e3)
    R⁺ = R Exp(dt ω)

``Exp`` is Rodrigues' formula ``I + A [φ]× + B [φ]×²`` with ``A = sin θ/θ``, ``B = (1 − cos θ)/θ²``; for
``θ² < 1e-4`` both use their Taylor series (to θ⁴), and the closed form takes ``θ = sqrt(max(θ², 1e-4))`` so
that neither branch of the ``if_else`` yields a non-finite value or derivative at ``ω = 0``.

Representation: ``R`` is a 3×3 matrix, 9 NLP variables per step (stored row-major: the state vector is
``z = (p, v, R[0, :], R[1, :], R[2, :])``, 15 entries).  The dynamics constraints are exact, and ``Exp`` is
orthogonal, so at a solution every ``R_k`` is a rotation to the solver's tolerance (no normalisation or
extra orthogonality constraint is needed; intermediate iterates need not be rotations).  ``x_0`` is a
parameter, not a variable: the decision variables are ``z_1 … z_N`` and ``u_0 … u_{N−1}``.

Cost (identical to ours)::

    Σ_{k<N} ‖x_k ⊟ x_k^d‖²_Q + ‖u_k − u_k^d‖²_Ru  +  ‖x_N ⊟ x_N^d‖²_P,
    x ⊟ x^d = (p − p^d, v − v^d, Log(R^dᵀ R)),

with diagonal weights.  ``Log`` is the exact SO(3) logarithm, written smoothly: with ``M = R^dᵀ R``,
``w = ½ vee(M − Mᵀ)`` (``= sin θ · axis``), ``c = (tr M − 1)/2`` (``= cos θ``) and ``s² = ‖w‖²``,
``Log = (θ / sin θ) w`` with ``θ / sin θ = atan2(s, c)/s``; for ``s² < 1e-8`` and ``c > 0`` it is the series
``(1/c)(1 − t²/3 + t⁴/5)``, ``t² = s²/c²``.  Its one limitation is the ``θ = π`` cut locus, where ``Log``
itself is not continuous (attitude errors of 180°; ``s`` is clamped there, so values stay finite but are
not ``Log``).  The ``x_0`` term is a constant, kept so that the reported cost is the whole sum above.

Warm start: after each solve the primal solution and the multipliers are shifted by one step (the last
stage is repeated) and used as the next initial guess.  ``warm_start_init_point`` is off by default (the
multipliers are then ignored by IPOPT); pass ``ipopt_options={"warm_start_init_point": "yes"}`` to use
them.  The first solve (or after ``reset()``) starts from the rollout of ``u_ref`` (clipped to the box)
from ``x0``.

``info["solve_time"]`` is ``time.perf_counter()`` around the solver call alone (no parameter packing or
result unpacking); IPOPT's own ``t_wall_total`` is reported too.  Returned inputs are clipped to the box
(IPOPT may overshoot a bound by its ``bound_relax_factor``, ~1e-8 relative).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

__all__ = ["CasadiQuadrotorMPC", "run_closed_loop"]

NX = 15  # p (3), v (3), R row-major (9)
NU = 4
NE = 9  # error: p, v, Log R

_EXP_EPS = 1e-4  # θ² below which Exp uses its Taylor series
_LOG_EPS = 1e-8  # sin²θ below which Log uses its series (when cos θ > 0)
_ROT_TOL = 1e-4  # loose: float32 inputs (e.g. from a torch simulator) must pass

_DEFAULT_IPOPT = {
    "print_level": 0,
    "sb": "yes",
    "tol": 1e-8,
    "acceptable_tol": 1e-6,
    "max_iter": 200,
    "warm_start_init_point": "no",
}


# --------------------------------------------------------------------------- symbolic building blocks


def _skew(ca, w):
    return ca.vertcat(
        ca.horzcat(0, -w[2], w[1]),
        ca.horzcat(w[2], 0, -w[0]),
        ca.horzcat(-w[1], w[0], 0),
    )


def _vee(ca, m):
    return ca.vertcat(m[2, 1], m[0, 2], m[1, 0])


def _so3_exp(ca, phi):
    """Rodrigues' formula, smooth at ``phi = 0`` (see the module docstring)."""
    th2 = ca.dot(phi, phi)
    th = ca.sqrt(ca.fmax(th2, _EXP_EPS))
    small = th2 < _EXP_EPS
    a = ca.if_else(small, 1 - th2 / 6 + th2**2 / 120, ca.sin(th) / th)
    b = ca.if_else(small, 0.5 - th2 / 24 + th2**2 / 720, (1 - ca.cos(th)) / (th * th))
    k = _skew(ca, phi)
    return ca.SX.eye(3) + a * k + b * ca.mtimes(k, k)


def _so3_log(ca, m):
    """Exact SO(3) logarithm of ``m`` (a rotation), smooth near the identity (see the module docstring)."""
    w = 0.5 * _vee(ca, m - m.T)
    c = 0.5 * (ca.trace(m) - 1)
    s2 = ca.dot(w, w)
    s = ca.sqrt(ca.fmax(s2, _LOG_EPS))
    c_safe = ca.fmax(c, 0.5)
    t2 = s2 / c_safe**2
    series = (1 - t2 / 3 + t2**2 / 5) / c_safe
    factor = ca.if_else(ca.logic_and(s2 < _LOG_EPS, c > 0.5), series, ca.atan2(s, c) / s)
    return factor * w


def _unpack(ca, z):
    p, v = z[0:3], z[3:6]
    rot = ca.reshape(z[6:15], 3, 3).T  # z holds R row-major; casadi reshapes column-major
    return p, v, rot


def _pack(ca, p, v, rot):
    return ca.vertcat(p, v, ca.reshape(rot.T, 9, 1))


def _build_step(ca, dt, g):
    z, u = ca.SX.sym("z", NX), ca.SX.sym("u", NU)
    p, v, rot = _unpack(ca, z)
    e3 = ca.DM([0.0, 0.0, 1.0])
    p_next = p + dt * v
    v_next = v + dt * (g * e3 - u[0] * ca.mtimes(rot, e3))
    rot_next = ca.mtimes(rot, _so3_exp(ca, dt * u[1:4]))
    return ca.Function("quad_step", [z, u], [_pack(ca, p_next, v_next, rot_next)], ["z", "u"], ["z_next"])


def _build_error(ca):
    z, zd = ca.SX.sym("z", NX), ca.SX.sym("zd", NX)
    p, v, rot = _unpack(ca, z)
    pd, vd, rotd = _unpack(ca, zd)
    err = ca.vertcat(p - pd, v - vd, _so3_log(ca, ca.mtimes(rotd.T, rot)))
    return ca.Function("quad_error", [z, zd], [err], ["z", "zd"], ["e"])


# --------------------------------------------------------------------------- numpy-side validation


def _vec(name, value, n):
    a = np.asarray(value, dtype=np.float64)
    if a.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite")
    return a


def _check_rotations(name, rot):
    eye = np.eye(3)
    err = np.abs(np.swapaxes(rot, -1, -2) @ rot - eye).max(initial=0.0)
    if err > _ROT_TOL or np.any(np.linalg.det(rot) <= 0):
        raise ValueError(
            f"{name} must hold rotation matrices (RᵀR = I, det R = +1); max |RᵀR − I| = {err:.2e}"
        )


def _state(name, x) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``x`` as ``(p (3,), v (3,), R (3, 3))`` from a tuple/list or a mapping with keys p, v, R."""
    if isinstance(x, Mapping):
        try:
            p, v, rot = x["p"], x["v"], x["R"]
        except KeyError as exc:
            raise ValueError(f"{name} must have keys 'p', 'v', 'R'; missing {exc}") from None
    else:
        if len(x) != 3:
            raise ValueError(f"{name} must be (p, v, R), got a sequence of length {len(x)}")
        p, v, rot = x
    p, v = _vec(f"{name}.p", p, 3), _vec(f"{name}.v", v, 3)
    rot = np.asarray(rot, dtype=np.float64)
    if rot.shape != (3, 3):
        raise ValueError(f"{name}.R must have shape (3, 3), got {rot.shape}")
    if not np.all(np.isfinite(rot)):
        raise ValueError(f"{name}.R must be finite")
    _check_rotations(f"{name}.R", rot)
    return p, v, rot


def _trajectory(name, x, n) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``x`` as ``(p (n, 3), v (n, 3), R (n, 3, 3))`` from a tuple/list or a mapping with keys p, v, R."""
    if isinstance(x, Mapping):
        try:
            parts = (x["p"], x["v"], x["R"])
        except KeyError as exc:
            raise ValueError(f"{name} must have keys 'p', 'v', 'R'; missing {exc}") from None
    else:
        if len(x) != 3:
            raise ValueError(f"{name} must be (p, v, R), got a sequence of length {len(x)}")
        parts = x
    out = []
    for part, label, shape in zip(parts, "pvR", [(n, 3), (n, 3), (n, 3, 3)]):
        a = np.asarray(part, dtype=np.float64)
        if a.shape != shape:
            raise ValueError(f"{name}.{label} must have shape {shape}, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name}.{label} must be finite")
        out.append(a)
    _check_rotations(f"{name}.R", out[2])
    return out[0], out[1], out[2]


def _to_z(p, v, rot) -> np.ndarray:
    """Stack states into the NLP layout: ``(..., 15)`` = p, v, R row-major."""
    lead = np.shape(p)[:-1]
    return np.concatenate([p, v, np.reshape(rot, (*lead, 9))], axis=-1)


def _from_z(z) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    z = np.asarray(z, dtype=np.float64)
    return z[..., 0:3].copy(), z[..., 3:6].copy(), z[..., 6:15].reshape(*z.shape[:-1], 3, 3).copy()


# --------------------------------------------------------------------------- the MPC


class CasadiQuadrotorMPC:
    """Nonlinear MPC of the quadrotor (multiple shooting, CasADi ``nlpsol`` + IPOPT), built once.

    Args:
        horizon: ``N ≥ 1`` control steps.
        dt: step (s), ``> 0``.
        Q: ``(9,)`` diagonal running weight on ``x ⊟ x^d`` (order p, v, R), ``≥ 0``.
        Ru: ``(4,)`` diagonal weight on ``u − u^d``, ``≥ 0``.
        P: ``(9,)`` diagonal terminal weight, ``≥ 0``, or a symmetric PSD ``(9, 9)`` matrix.
        u_lower, u_upper: ``(4,)`` input box, ``u_lower ≤ u_upper`` (``±inf`` allowed).
        g: gravity (m/s²).
        ipopt_options: IPOPT options (bare IPOPT names, e.g. ``{"tol": 1e-6}``) that override the defaults
            ``print_level 0, sb yes, tol 1e-8, acceptable_tol 1e-6, max_iter 200, warm_start_init_point no``.
    """

    def __init__(
        self,
        horizon: int,
        dt: float,
        Q,
        Ru,
        P,
        u_lower,
        u_upper,
        g: float = 9.81,
        ipopt_options: Mapping[str, Any] | None = None,
    ):
        if isinstance(horizon, bool) or not isinstance(horizon, (int, np.integer)) or horizon < 1:
            raise ValueError(f"horizon must be a positive int, got {horizon!r}")
        dt, g = float(dt), float(g)
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be finite and > 0, got {dt}")
        if not np.isfinite(g):
            raise ValueError(f"g must be finite, got {g}")
        self.horizon, self.dt, self.g = int(horizon), dt, g
        self.Q, self.Ru = _vec("Q", Q, NE), _vec("Ru", Ru, NU)
        Pa = np.asarray(P, dtype=np.float64)
        if Pa.shape == (NE, NE):  # a full terminal weight (e.g. the DARE solution)
            if not np.all(np.isfinite(Pa)) or not np.allclose(Pa, Pa.T, rtol=0, atol=1e-9 * np.abs(Pa).max()):
                raise ValueError("P must be finite and symmetric")
            if np.linalg.eigvalsh(0.5 * (Pa + Pa.T)).min() < -1e-9 * np.abs(Pa).max():
                raise ValueError("P must be positive semidefinite")
            self.P = 0.5 * (Pa + Pa.T)
        else:
            self.P = np.diag(_vec("P", P, NE))
        for name, w in (("Q", self.Q), ("Ru", self.Ru), ("P", np.diag(self.P))):
            if np.any(w < 0):
                raise ValueError(f"{name} must be >= 0, got {w}")
        lo, hi = np.asarray(u_lower, dtype=np.float64), np.asarray(u_upper, dtype=np.float64)
        if lo.shape != (NU,) or hi.shape != (NU,):
            raise ValueError(f"u_lower and u_upper must have shape (4,), got {lo.shape} and {hi.shape}")
        if np.any(np.isnan(lo)) or np.any(np.isnan(hi)) or np.any(lo > hi):
            raise ValueError(f"need u_lower <= u_upper (no NaN), got u_lower={lo}, u_upper={hi}")
        self.u_lower, self.u_upper = lo, hi
        opts = dict(_DEFAULT_IPOPT)
        for key, val in (ipopt_options or {}).items():
            opts[key[6:] if key.startswith("ipopt.") else key] = val
        self.ipopt_options = opts
        self._build()
        self.reset()

    # ----------------------------------------------------------------- construction

    def _build(self) -> None:
        import casadi as ca

        n = self.horizon
        self._step_fn = _build_step(ca, self.dt, self.g)
        self._error_fn = _build_error(ca)
        self._rollout_fn = self._step_fn.mapaccum("quad_rollout", n)

        z_vars = ca.SX.sym("Z", NX, n)  # z_1 … z_N
        u_vars = ca.SX.sym("U", NU, n)  # u_0 … u_{N-1}
        z0 = ca.SX.sym("z0", NX)
        zref = ca.SX.sym("Zref", NX, n + 1)
        uref = ca.SX.sym("Uref", NU, n)
        q, ru, pw = ca.DM(self.Q), ca.DM(self.Ru), ca.DM(self.P)

        cost = 0
        cons = []
        z_prev = z0
        for k in range(n):
            e = self._error_fn(z_prev, zref[:, k])
            du = u_vars[:, k] - uref[:, k]
            cost += ca.dot(q * e, e) + ca.dot(ru * du, du)
            cons.append(z_vars[:, k] - self._step_fn(z_prev, u_vars[:, k]))
            z_prev = z_vars[:, k]
        e = self._error_fn(z_prev, zref[:, n])
        cost += ca.dot(e, ca.mtimes(pw, e))

        # Decision vector: (z_1, u_0, z_2, u_1, …) interleaved per stage would be equivalent; keep blocks.
        w = ca.vertcat(ca.reshape(z_vars, -1, 1), ca.reshape(u_vars, -1, 1))
        par = ca.vertcat(z0, ca.reshape(zref, -1, 1), ca.reshape(uref, -1, 1))
        nlp = {"x": w, "p": par, "f": cost, "g": ca.vertcat(*cons)}
        nlp_opts = {"print_time": False, "error_on_fail": False, "ipopt": dict(self.ipopt_options)}
        self._solver = ca.nlpsol("quad_mpc", "ipopt", nlp, nlp_opts)
        self._nw, self._ng = NX * n + NU * n, NX * n

        big = np.inf
        self._lbw = np.concatenate([np.full(NX * n, -big), np.tile(self.u_lower, n)])
        self._ubw = np.concatenate([np.full(NX * n, big), np.tile(self.u_upper, n)])

    def reset(self) -> None:
        """Forget the warm start (the next ``step`` starts from the rollout of ``u_ref``)."""
        self._warm = None

    # ----------------------------------------------------------------- numeric helpers (also used by tests)

    def dynamics(self, x, u) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One step of the model inside the NLP, evaluated numerically: ``(p, v, R)`` at ``k + 1``."""
        p, v, rot = _state("x", x)
        u = _vec("u", u, NU)
        z = np.asarray(self._step_fn(_to_z(p, v, rot), u)).reshape(NX)
        return _from_z(z)

    def state_error(self, x, x_ref) -> np.ndarray:
        """``x ⊟ x_ref = (p − p^d, v − v^d, Log(R^dᵀ R))`` as used in the cost, ``(9,)``."""
        p, v, rot = _state("x", x)
        pd, vd, rotd = _state("x_ref", x_ref)
        return np.asarray(self._error_fn(_to_z(p, v, rot), _to_z(pd, vd, rotd))).reshape(NE)

    # ----------------------------------------------------------------- the MPC step

    def step(self, x0, x_ref, u_ref) -> tuple[np.ndarray, dict[str, Any]]:
        """Solve the NLP from ``x0`` and return ``(u0 (4,), info)``.

        Args:
            x0: ``(p (3,), v (3,), R (3, 3))`` (tuple or mapping with keys p, v, R).
            x_ref: ``(p (N+1, 3), v (N+1, 3), R (N+1, 3, 3))`` reference states ``x_0^d … x_N^d``.
            u_ref: ``(N, 4)`` reference inputs ``u_0^d … u_{N−1}^d``.

        ``info``: ``solve_time`` (s, solver call only), ``success`` (bool), ``status`` (IPOPT's return
        status), ``iterations``, ``cost`` (NLP objective at the returned point), ``ipopt_time`` (IPOPT's
        ``t_wall_total``), ``u`` (N, 4) and ``x`` = ``(p, v, R)`` of the whole planned trajectory (N+1).
        """
        n = self.horizon
        z0 = _to_z(*_state("x0", x0))
        zref = _to_z(*_trajectory("x_ref", x_ref, n + 1))
        uref = np.asarray(u_ref, dtype=np.float64)
        if uref.shape != (n, NU):
            raise ValueError(f"u_ref must have shape ({n}, {NU}), got {uref.shape}")
        if not np.all(np.isfinite(uref)):
            raise ValueError("u_ref must be finite")

        if self._warm is None:
            u_guess = np.clip(uref, self.u_lower, self.u_upper)
            z_guess = np.asarray(self._rollout_fn(z0, u_guess.T)).T  # (N, 15): z_1 … z_N
            w0 = np.concatenate([z_guess.reshape(-1), u_guess.reshape(-1)])
            lam_w0, lam_g0 = np.zeros(self._nw), np.zeros(self._ng)
        else:
            w0, lam_w0, lam_g0 = self._warm
        par = np.concatenate([z0, zref.reshape(-1), uref.reshape(-1)])

        args = dict(x0=w0, p=par, lbx=self._lbw, ubx=self._ubw, lbg=0.0, ubg=0.0)
        args.update(lam_x0=lam_w0, lam_g0=lam_g0)
        t0 = time.perf_counter()
        sol = self._solver(**args)
        solve_time = time.perf_counter() - t0
        stats = self._solver.stats()

        w = np.asarray(sol["x"]).reshape(-1)
        z_sol = w[: NX * n].reshape(n, NX)
        u_sol = w[NX * n :].reshape(n, NU)
        lam_w = np.asarray(sol["lam_x"]).reshape(-1)
        lam_g = np.asarray(sol["lam_g"]).reshape(-1)
        if np.all(np.isfinite(w)) and np.all(np.isfinite(lam_w)) and np.all(np.isfinite(lam_g)):
            self._warm = _shift(w, lam_w, lam_g, n)
        else:
            self._warm = None

        # IPOPT relaxes bounds by ~bound_relax_factor (1e-8 relative): return inputs inside the box exactly.
        u_sol = np.clip(u_sol, self.u_lower, self.u_upper)
        p_plan, v_plan, r_plan = _from_z(np.vstack([z0, z_sol]))
        info = {
            "solve_time": solve_time,
            "success": bool(stats.get("success", False)),
            "status": str(stats.get("return_status", "unknown")),
            "iterations": int(stats.get("iter_count", -1)),
            "cost": float(sol["f"]),
            "ipopt_time": float(stats.get("t_wall_total", np.nan)),
            "u": u_sol.copy(),
            "x": (p_plan, v_plan, r_plan),
        }
        return u_sol[0].copy(), info


def _shift(w, lam_w, lam_g, n):
    """Shift a solution (and its multipliers) one stage ahead, repeating the last stage."""

    def shift_blocks(a, width):
        blocks = a.reshape(n, width)
        return np.vstack([blocks[1:], blocks[-1:]]).reshape(-1)

    nz = NX * n
    w_s = np.concatenate([shift_blocks(w[:nz], NX), shift_blocks(w[nz:], NU)])
    lw_s = np.concatenate([shift_blocks(lam_w[:nz], NX), shift_blocks(lam_w[nz:], NU)])
    lg_s = shift_blocks(lam_g, NX)
    return w_s, lw_s, lg_s


# --------------------------------------------------------------------------- closed loop


def run_closed_loop(
    mpc: CasadiQuadrotorMPC,
    simulate: Callable[[tuple[np.ndarray, np.ndarray, np.ndarray], np.ndarray], Any],
    x0,
    ref: Sequence | Mapping,
    steps: int,
) -> dict[str, Any]:
    """Receding-horizon loop: at each step solve from the current state, apply ``u0``, simulate.

    Args:
        mpc: the controller (its warm start is reset first).
        simulate: ``simulate(x, u) -> x_next`` with ``x = (p, v, R)`` numpy arrays and ``u (4,)``; it may
            return ``(p, v, R)`` or a mapping with keys p, v, R (e.g. a wrapper around our simulator).
        x0: initial state ``(p, v, R)``.
        ref: reference ``(p (T, 3), v (T, 3), R (T, 3, 3), u (T, 4))`` (or a mapping with keys p, v, R, u)
            indexed by time step; the window at step ``t`` is states ``t … t+N`` and inputs ``t … t+N−1``,
            and indices past ``T − 1`` repeat the last entry (so a constant reference may have ``T = 1``).
        steps: number of closed-loop steps.

    Returns a dict of arrays: ``p (steps+1, 3)``, ``v (steps+1, 3)``, ``R (steps+1, 3, 3)``, ``u (steps, 4)``,
    ``solve_time (steps,)`` (s), ``success (steps,)`` bool, ``iterations (steps,)``, ``cost (steps,)`` and
    ``status`` (list of IPOPT return statuses).
    """
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 0:
        raise ValueError(f"steps must be a non-negative int, got {steps!r}")
    if not callable(simulate):
        raise TypeError("simulate must be callable: simulate(x, u) -> x_next")
    if isinstance(ref, Mapping):
        try:
            parts = (ref["p"], ref["v"], ref["R"], ref["u"])
        except KeyError as exc:
            raise ValueError(f"ref must have keys 'p', 'v', 'R', 'u'; missing {exc}") from None
    else:
        if len(ref) != 4:
            raise ValueError(f"ref must be (p, v, R, u), got a sequence of length {len(ref)}")
        parts = ref
    r_u = np.asarray(parts[3], dtype=np.float64)
    if r_u.ndim != 2 or r_u.shape[1] != NU or r_u.shape[0] < 1:
        raise ValueError(f"ref.u must have shape (T, 4) with T >= 1, got {r_u.shape}")
    t_len = r_u.shape[0]
    r_p, r_v, r_r = _trajectory("ref", parts[:3], t_len)

    n = mpc.horizon
    mpc.reset()
    p, v, rot = _state("x0", x0)
    ps, vs, rs = [p], [v], [rot]
    us, times, ok, iters, costs, status = [], [], [], [], [], []
    for t in range(int(steps)):
        idx_x = np.minimum(np.arange(t, t + n + 1), t_len - 1)
        idx_u = idx_x[:-1]
        u, info = mpc.step((p, v, rot), (r_p[idx_x], r_v[idx_x], r_r[idx_x]), r_u[idx_u])
        p, v, rot = _state(f"simulate output at step {t}", simulate((p, v, rot), u))
        ps.append(p)
        vs.append(v)
        rs.append(rot)
        us.append(u)
        times.append(info["solve_time"])
        ok.append(info["success"])
        iters.append(info["iterations"])
        costs.append(info["cost"])
        status.append(info["status"])
    return {
        "p": np.array(ps),
        "v": np.array(vs),
        "R": np.array(rs),
        "u": np.array(us).reshape(-1, NU),
        "solve_time": np.array(times, dtype=np.float64),
        "success": np.array(ok, dtype=bool),
        "iterations": np.array(iters, dtype=np.int64),
        "cost": np.array(costs, dtype=np.float64),
        "status": status,
    }
