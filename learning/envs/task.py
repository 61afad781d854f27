"""A control task: the one definition an environment, a vector environment, an MPC expert and an evaluation
share.

A :class:`Task` is a frozen dataclass around a :class:`controllers.dynamics.System` (the dynamics are the
system's ``step``, never re-implemented) that adds, batched over any number of environments in torch:
the initial-state distribution (from uniforms, see :mod:`learning._counter_rng`), the observation, the
reward, termination, success and a task error, the action scaling, the rendering of one state, and the
MPC cost that solves it.  Actions are *normalized*: the action space is ``[-1, 1]^m`` (what RL libraries
expect) and ``u = action · u_max`` is the physical control; actions outside the box are **clipped** to it
(as :class:`gymnasium.wrappers.ClipAction` would), a non-finite action ends the episode (see the envs).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch
from torch import Tensor

__all__ = ["Task", "ErrorStateExpert", "angle_wrap", "terminal_weighted", "hi", "lo"]


def angle_wrap(a: Tensor) -> Tensor:
    """Angle mapped to ``[-π, π)``."""
    return torch.remainder(a + math.pi, 2 * math.pi) - math.pi


def hi(v) -> float:
    """Largest value of a float or tensor model parameter (for bounds)."""
    return float(torch.as_tensor(v).detach().to(torch.float64).max())


def lo(v) -> float:
    """Smallest value of a float or tensor model parameter (for bounds)."""
    return float(torch.as_tensor(v).detach().to(torch.float64).min())


def terminal_weighted(q_diag: Tensor, horizon: int, factor: float = 10.0) -> Tensor:
    """``(horizon+1, n, n)`` diagonal state weights, the terminal one ``factor`` times the running one."""
    Q = torch.diag_embed(q_diag).expand(horizon + 1, -1, -1).clone()
    Q[-1] *= factor
    return Q


@dataclass(frozen=True, eq=False)
class Task:
    """Base class of the tasks (subclasses are frozen dataclasses).

    Subclasses set the class attributes and implement the methods below; every method takes and returns
    batched tensors ``(N, ·)`` in the dtype/device of its input.
    """

    #: registered name (``liecontrol/<name>-v0``)
    name: ClassVar[str] = ""
    #: dimension of the observation and number of uniforms the initial state needs
    obs_dim: ClassVar[int] = 0
    n_noise: ClassVar[int] = 0

    max_episode_steps: int = 200

    # --- to implement -------------------------------------------------------------------------------
    @property
    def system(self):
        raise NotImplementedError

    def u_max(self) -> tuple[float, ...]:
        """Symmetric bound of each physical control (the action ``±1`` maps to ``±u_max``)."""
        raise NotImplementedError

    def obs_high(self) -> np.ndarray:
        """Bound of ``|observation|`` per component: finite, and provably never exceeded within an
        episode of at most ``max_episode_steps`` steps (each task gives its argument)."""
        raise NotImplementedError

    def initial_state(self, noise: Tensor) -> Tensor:
        """States ``(N, n)`` from uniforms ``noise (N, n_noise)`` in ``[0, 1]``."""
        raise NotImplementedError

    def observe(self, x: Tensor) -> Tensor:
        raise NotImplementedError

    def reward(self, x: Tensor, u: Tensor, x_next: Tensor) -> Tensor:
        raise NotImplementedError

    def terminated(self, x: Tensor) -> Tensor:
        """``(N,)`` bool: the state is terminal (default: never)."""
        return torch.zeros(x.shape[:-1], dtype=torch.bool, device=x.device)

    def error(self, x: Tensor) -> Tensor:
        """``(N,)`` distance of the state to the goal, in the task's natural unit."""
        raise NotImplementedError

    def success(self, x: Tensor) -> Tensor:
        """``(N,)`` bool: the goal is reached at state ``x`` (judged at the end of an episode)."""
        raise NotImplementedError

    def state_from_obs(self, obs: Tensor) -> Tensor:
        """The state ``(N, n)`` an observation was made from (observations here are full-state)."""
        raise NotImplementedError

    def mpc_cost(self, horizon: int, *, dtype=torch.float64, device=None):
        """A :class:`controllers.costs.QuadraticCost` over ``horizon`` steps that an MPC solves the task
        with (controls in physical units)."""
        raise NotImplementedError

    def frame(self, x: np.ndarray, size: int = 256) -> np.ndarray:
        """``(size, size, 3)`` uint8 image of one state ``x (n,)``."""
        raise NotImplementedError

    def safe_action_box(self, x: Tensor) -> tuple[Tensor, Tensor] | None:
        """``(lo, hi)`` bounds ``(N, m)`` on the normalized action at states ``x (N, n)`` that keep the next
        state inside the limits whose crossing ends the episode (a one-step safety filter; an MPC without
        those state constraints clips its first control to it), or ``None`` (the default): no such limits.
        ``lo ≤ hi`` everywhere, both within ``[-1, 1]``."""
        return None

    def expert(self, horizon: int | None = None, **kwargs):
        """The task's own MPC expert (a :class:`learning.policies.Policy`), or ``None`` (the default): the
        iLQR :class:`learning.policies.MPCExpert` on ``system`` and ``mpc_cost`` solves it.  Tasks whose
        MPC is not an iLQR on a vector state (the quadrotor's error-state MPC on its manifold) override it;
        :func:`learning.policies.task_expert` picks."""
        return None

    # --- shared -------------------------------------------------------------------------------------
    @property
    def n(self) -> int:
        return self.system.n

    @property
    def m(self) -> int:
        return self.system.m

    def u_scale(self, dtype: torch.dtype, device) -> Tensor:
        return torch.tensor(self.u_max(), dtype=dtype, device=device)

    def step(self, x: Tensor, u: Tensor) -> Tensor:
        """One step of the system's own dynamics (physical control ``u``)."""
        return self.system.step(x, u, 0)

    def transition(self, x: Tensor, action: Tensor, scale: Tensor):
        """The environment step shared by the single and the vector env, batched.

        ``action (N, m)`` normalized; non-finite entries make the element *invalid* (its control is taken
        as zero so that state and reward stay finite, and the env ends the episode with a flag); finite
        ones are clipped to ``[-1, 1]``.  A step whose reward is not finite (a state that blew up) is
        invalid too.  Returns ``(x_next, u, reward, terminated, invalid)``.
        """
        ok = torch.isfinite(action).all(-1)
        u = action.nan_to_num(0.0, 0.0, 0.0).clamp_(-1.0, 1.0).mul_(scale)
        x1 = self.step(x, u)
        r = self.reward(x, u, x1)
        invalid = ~(ok & torch.isfinite(r))
        return x1, u, r, self.terminated(x1), invalid


class ErrorStateExpert:
    """What the experts built on :class:`controllers.manifold_mpc.ErrorStateMPC` share (a
    :class:`learning.policies.Policy`): the previous plan, shifted by one step, warm-starts the next QP
    (per element; :meth:`reset` forgets it where an episode ended), and :meth:`info` gives the last solve's
    per-element iterations and certified convergence.  Subclasses call :meth:`_warm_start` and
    :meth:`_remember` around their ``solve``."""

    def __init__(self) -> None:
        self._warm: Tensor | None = None
        self._info: dict[str, Tensor] | None = None

    def _warm_start(self, u_ref: Tensor) -> Tensor | None:
        """The shifted previous plan for a solve about ``u_ref`` ``(N, H, m)`` (``u_ref`` where an element
        was reset), or ``None`` when the batch changed."""
        w = self._warm
        if w is None or w.shape != u_ref.shape:
            return None
        return torch.where(torch.isfinite(w), w, u_ref)

    def _remember(self, sol, device) -> None:
        self._warm = torch.cat([sol.U[:, 1:], sol.U[:, -1:]], 1)
        self._info = {"iterations": sol.status.iterations.to(device),
                      "converged": sol.status.converged.to(device)}

    def reset(self, done: Tensor | None = None) -> None:
        if done is None or self._warm is None or done.shape != self._warm.shape[:1]:
            self._warm = None
        else:
            self._warm = torch.where(done.to(self._warm.device)[:, None, None], torch.nan, self._warm)
        self._info = None

    def info(self) -> dict[str, Tensor] | None:
        return self._info
