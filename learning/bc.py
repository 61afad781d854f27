"""Behaviour cloning from an expert (issue 12 §6): demonstrations, an MLP policy, an MPC with a learned
cost, and a study of both against the number of demonstrations.

Our own small trainer (the ``imitation`` package pins an old gymnasium and stable-baselines3):

* :func:`collect_demos` runs any policy (:func:`learning.policies.as_policy`; ``"mpc"`` for the task's
  :class:`~learning.policies.MPCExpert`) on a :class:`~learning.vector.TaskVectorEnv`, ``num_envs``
  episodes at a time, and records every control step as one sample of a :class:`Demos`: the
  observation, the *normalized* action (clipped to ``[-1, 1]``, what the env applied), the env's state,
  the episode index and the step; per episode its env seed, return and success.  Episode ``i`` is the
  one of env seed ``seed + i`` (identical to :class:`~learning.envs.single.TaskEnv` reset with that
  seed).  :meth:`Demos.save` / :meth:`Demos.load` use ``torch.save`` of plain tensors and
  ``torch.load(..., weights_only=True)``: no pickled objects.  :meth:`Demos.split` holds out whole
  episodes.
* :func:`train_mlp_policy`: an MLP ``obs → tanh(·) ∈ [-1, 1]^m`` (inputs standardized by the training
  set's mean and std, kept as buffers) fitted by MSE to the normalized actions; Adam, minibatches,
  deterministic given ``seed``.
* :func:`train_mpc_cost`: an :class:`~controllers.mpc.MPCPolicy` on ``task.system`` (the expert's model
  and horizon) whose cost is a :class:`LearnableQuadraticCost` — diagonal state and control weights
  (log-parametrized, so positive) and optionally the target, with the expert cost's terminal factor —
  initialised away from the expert's (all weights 1 by default) and trained by backpropagation through
  the MPC solve (implicit iLQR gradients) on minibatches of demo states:
  ``loss = MSE(u_mpc / u_max, a_expert)``.  Only the cost's *shape* is given (diagonal, terminal factor,
  target unless ``learn_target``); the weights are learned.  Since the MPC's action does not change when
  the whole cost is scaled, the weights are only identifiable up to a common factor: the history reports
  them normalized by the first state weight, next to the expert's.
* :func:`bc_study`: one demo pool (``max(demo_counts)`` training episodes + held-out episodes); for each
  count ``k`` both learners are trained on the first ``k`` episodes, and the held-out action MSE (on the
  held-out episodes' states) and the closed-loop success and return (:func:`learning.evaluate.evaluate`
  on fresh seeds, batched) are reported as JSON-serialisable records.

The MPC learner plans from the same state the expert planned from: ``task.state_from_obs`` with the angles
taken on the expert's branch around its target (the hysteresis of :class:`~learning.policies.MPCAdapter`,
replayed along each episode).  Swing-up planning problems have several local optima and the expert's
solves are warm-started along its trajectory: a cold-started solve with the expert's *own* cost disagrees
with it badly (held-out MSE ≈ 0.8 on the pendulum), and a solve warm-started from the demo's own future
actions (``warm_start="demo"``) stays where it starts whatever the cost (weak gradients).  So by default
(``warm_start="sequential"``) training replays demo episodes in order as the expert ran them: zero
controls at step 0, then the MPC's own previous plan, one gradient step per ``window`` steps; the
held-out error of an MPC is measured the same way (:func:`mpc_action_mse`: the MPC warm-starts itself
along each held-out episode's observations), where the expert's cost gives zero (about 1e-17).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import torch
from gymnasium.vector import AutoresetMode
from torch import Tensor, nn

from learning.envs.single import as_action, as_device, as_dtype, int_arg, make_task
from learning.envs.task import Task
from learning.policies import DEFAULT_HORIZON, MPCAdapter, angle_dims, as_policy
from learning.vector import TaskVectorEnv

__all__ = ["Demos", "collect_demos", "MLPPolicy", "train_mlp_policy", "LearnableQuadraticCost",
           "expert_cost_weights", "train_mpc_cost", "mpc_policy", "mpc_action_mse", "action_mse",
           "bc_study", "format_table"]

_FORMAT = "liecontrol.bc.Demos/1"


# ------------------------------------------------------------------------------------------- demos
@dataclass(frozen=True, eq=False)
class Demos:
    """Expert demonstrations: ``S`` samples (control steps) from ``E`` episodes.

    Per sample: ``obs (S, obs_dim)``, ``action (S, m)`` normalized and clipped to ``[-1, 1]``,
    ``state (S, n)`` the env's state, ``episode (S,)`` int64 in ``[0, E)``, ``step (S,)`` int64 (time in
    the episode).  Samples are ordered by episode, then step.  Per episode: ``seeds (E,)`` the env seeds,
    ``returns (E,)``, ``success (E,)`` bool (the task's success at the final state, episode valid),
    ``length (E,)`` steps.  ``task`` is the task's name.
    """

    obs: Tensor
    action: Tensor
    state: Tensor
    episode: Tensor
    step: Tensor
    seeds: Tensor
    returns: Tensor
    success: Tensor
    length: Tensor
    task: str = ""

    def __post_init__(self) -> None:
        S, E = self.obs.shape[0], self.seeds.shape[0]
        for f in ("action", "state", "episode", "step"):
            if getattr(self, f).shape[0] != S:
                raise ValueError(f"Demos: field '{f}' has {getattr(self, f).shape[0]} rows, obs has {S}")
        for f in ("returns", "success", "length"):
            if getattr(self, f).shape != (E,):
                raise ValueError(f"Demos: field '{f}' must have shape ({E},), got "
                                 f"{tuple(getattr(self, f).shape)}")

    def __len__(self) -> int:
        return int(self.obs.shape[0])

    @property
    def episodes(self) -> int:
        return int(self.seeds.shape[0])

    @property
    def sample_success(self) -> Tensor:
        """``(S,)`` bool: the success of each sample's episode."""
        return self.success[self.episode]

    def select(self, episodes) -> Demos:
        """The demos of the given episode indices (renumbered ``0..k-1`` in the given order)."""
        idx = torch.as_tensor(episodes, dtype=torch.int64).reshape(-1)
        new = torch.full((self.episodes,), -1, dtype=torch.int64)
        new[idx] = torch.arange(idx.numel())
        keep = new[self.episode] >= 0
        ep = new[self.episode[keep]]
        span = int(self.step.max()) + 1 if len(self) else 1
        order = torch.argsort(ep * span + self.step[keep], stable=True)
        pick = torch.nonzero(keep).flatten()[order]
        return Demos(obs=self.obs[pick], action=self.action[pick], state=self.state[pick],
                     episode=new[self.episode[pick]], step=self.step[pick], seeds=self.seeds[idx],
                     returns=self.returns[idx], success=self.success[idx], length=self.length[idx],
                     task=self.task)

    def first(self, k: int) -> Demos:
        """The first ``k`` episodes."""
        return self.select(torch.arange(min(int(k), self.episodes)))

    def split(self, heldout: int | float) -> tuple[Demos, Demos]:
        """``(train, held_out)`` by episode: the last ``heldout`` episodes (an int), or that fraction of
        them (a float in ``(0, 1)``, at least one) are held out."""
        E = self.episodes
        k = int(heldout) if isinstance(heldout, int) else max(1, int(round(float(heldout) * E)))
        if not 0 < k < E:
            raise ValueError(f"Demos.split: cannot hold out {heldout!r} of {E} episodes")
        return self.select(torch.arange(E - k)), self.select(torch.arange(E - k, E))

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {f.name: getattr(self, f.name) for f in fields(self)}
        d["format"] = _FORMAT
        return d

    def save(self, path) -> None:
        """``torch.save`` of a dict of plain tensors and strings (loadable with ``weights_only=True``)."""
        torch.save({k: (v.detach().cpu().contiguous() if isinstance(v, Tensor) else v)
                    for k, v in self.to_dict().items()}, Path(path))

    @classmethod
    def load(cls, path) -> Demos:
        d = torch.load(Path(path), map_location="cpu", weights_only=True)
        if not isinstance(d, dict) or d.get("format") != _FORMAT:
            raise ValueError(f"Demos.load: {path} is not a {_FORMAT} file")
        return cls(**{f.name: d[f.name] for f in fields(cls)})


@torch.no_grad()
def collect_demos(expert: Any, task: Task | str = "PendulumSwingUp", episodes: int = 10, seed: int = 0, *,
                  num_envs: int = 16, dtype=torch.float64, device: torch.device | str = "cpu",
                  max_episode_steps: int | None = None) -> Demos:
    """Roll out ``expert`` (anything :func:`~learning.policies.as_policy` accepts) for ``episodes``
    episodes, the one of env seed ``seed + i`` being episode ``i``, ``num_envs`` at a time (module
    docstring).  An episode whose action is not finite ends there (that step is not recorded) and counts
    as unsuccessful."""
    task = make_task(task)
    if max_episode_steps is not None and max_episode_steps != task.max_episode_steps:
        import dataclasses

        task = dataclasses.replace(task, max_episode_steps=int_arg(max_episode_steps, "max_episode_steps",
                                                                   "collect_demos"))
    dtype, device = as_dtype(dtype), as_device(device, "collect_demos")
    episodes = int_arg(episodes, "episodes", "collect_demos")
    pol = as_policy(expert, task)
    N = min(int_arg(num_envs, "num_envs", "collect_demos"), episodes)
    T = task.max_episode_steps
    fkw = dict(dtype=dtype, device=device)
    obs_l, act_l, st_l, ep_l, t_l = [], [], [], [], []
    returns = torch.zeros(episodes, **fkw)
    success = torch.zeros(episodes, dtype=torch.bool, device=device)
    length = torch.zeros(episodes, dtype=torch.int64, device=device)
    envs: dict[int, TaskVectorEnv] = {}
    for start in range(0, episodes, N):
        idx = torch.arange(start, min(start + N, episodes), device=device)
        n = idx.numel()
        if n not in envs:
            envs[n] = TaskVectorEnv(task, n, max_episode_steps=T, autoreset_mode=AutoresetMode.NEXT_STEP,
                                    device=device, dtype=dtype, output="torch")
        env = envs[n]
        obs, _ = env.reset(seed=[seed + int(i) for i in idx])
        pol.reset(None)
        active = torch.ones(n, dtype=torch.bool, device=device)
        bad = torch.zeros(n, dtype=torch.bool, device=device)
        ret = torch.zeros(n, **fkw)
        x_final = env.state
        for t in range(T):
            a = pol.act(obs)
            a = as_action(a, dtype, "the expert's action", device).reshape(n, task.m)
            finite = torch.isfinite(a).all(-1)
            bad |= active & ~finite
            active = active & finite
            if not bool(active.any()):
                break
            a = torch.where(active[:, None], a.nan_to_num(0.0, 0.0, 0.0).clamp(-1.0, 1.0), 0.0)
            rec = torch.nonzero(active).flatten()
            obs_l.append(obs[rec])
            act_l.append(a[rec])
            st_l.append(env.state[rec])
            ep_l.append(idx[rec])
            t_l.append(torch.full((rec.numel(),), t, dtype=torch.int64, device=device))
            obs, r, term, trunc, infos = env.step(a)
            inv = infos.get("invalid")
            if inv is not None:
                bad |= active & inv.to(torch.bool)
            ret += torch.where(active, r, 0.0)
            length[idx] += active.long()
            x_final = torch.where(active[:, None], env.state, x_final)
            ended = active & (term | trunc)
            active = active & ~ended
            pol.reset(ended)
            if not bool(active.any()):
                break
        returns[idx] = ret
        success[idx] = task.success(x_final) & ~bad
    ep = torch.cat(ep_l)
    st = torch.cat(t_l)
    order = torch.argsort(ep * (T + 1) + st, stable=True)
    return Demos(obs=torch.cat(obs_l)[order], action=torch.cat(act_l)[order], state=torch.cat(st_l)[order],
                 episode=ep[order], step=st[order],
                 seeds=torch.arange(seed, seed + episodes, dtype=torch.int64, device=device),
                 returns=returns, success=success, length=length, task=task.name)


# ------------------------------------------------------------------------------------------- MLP
class MLPPolicy(nn.Module):
    """``obs (N, obs_dim) → tanh(MLP((obs - mean) / std)) (N, m)``: a normalized action in ``[-1, 1]``.
    ``mean``/``std`` are buffers (the training set's), so the module is a plain ``state_dict``."""

    def __init__(self, obs_dim: int, m: int, hidden=(64, 64), *, mean: Tensor | None = None,
                 std: Tensor | None = None, activation: type[nn.Module] = nn.Tanh):
        super().__init__()
        layers: list[nn.Module] = []
        d = obs_dim
        for h in hidden:
            layers += [nn.Linear(d, int(h)), activation()]
            d = int(h)
        layers.append(nn.Linear(d, m))
        self.net = nn.Sequential(*layers)
        self.register_buffer("mean", torch.zeros(obs_dim) if mean is None else mean.detach().clone())
        self.register_buffer("std", torch.ones(obs_dim) if std is None else std.detach().clone())

    def forward(self, obs: Tensor) -> Tensor:
        return torch.tanh(self.net((obs - self.mean) / self.std))


def action_mse(policy_fn, demos: Demos) -> float:
    """Mean squared error of ``policy_fn(obs)`` against the demos' normalized actions (per component)."""
    with torch.no_grad():
        a = policy_fn(demos.obs)
        return float(((a.to(demos.action.dtype) - demos.action) ** 2).mean())


def _module_fn(model: nn.Module):
    dtype = next(model.parameters()).dtype
    return lambda o: model(o.to(dtype))


def train_mlp_policy(demos: Demos, hidden=(64, 64), epochs: int = 200, lr: float = 3e-3,
                     batch_size: int = 256, seed: int = 0, *, weight_decay: float = 0.0,
                     dtype=torch.float32, val: Demos | None = None) -> tuple[MLPPolicy, dict[str, Any]]:
    """Fit an :class:`MLPPolicy` to the demos by MSE on the normalized actions (Adam, shuffled
    minibatches).  Deterministic given ``seed`` (the initialization and the shuffling use their own
    generators).  History: ``loss`` per epoch (training MSE), ``val_mse`` per epoch when ``val`` is given,
    ``time_s``."""
    if len(demos) == 0:
        raise ValueError("train_mlp_policy: no samples")
    dtype = as_dtype(dtype)
    X = demos.obs.to(dtype)
    Y = demos.action.to(dtype)
    mean = X.mean(0)
    std = X.std(0, unbiased=False).clamp(min=1e-3)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = MLPPolicy(X.shape[1], Y.shape[1], hidden, mean=mean, std=std).to(dtype)
    gen = torch.Generator().manual_seed(seed)
    opt = torch.optim.Adam(model.parameters(), lr=lr, weight_decay=weight_decay)
    S = X.shape[0]
    hist: dict[str, Any] = {"loss": [], "val_mse": []}
    t0 = time.perf_counter()
    for _ in range(int(epochs)):
        perm = torch.randperm(S, generator=gen)
        tot = 0.0
        for i in range(0, S, batch_size):
            b = perm[i:i + batch_size]
            loss = ((model(X[b]) - Y[b]) ** 2).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            tot += float(loss.detach()) * b.numel()
        hist["loss"].append(tot / S)
        if val is not None:
            hist["val_mse"].append(action_mse(lambda o: model(o.to(dtype)), val))
    hist["time_s"] = time.perf_counter() - t0
    model.eval()
    return model, hist


# ------------------------------------------------------------------------------------------- MPC cost
class LearnableQuadraticCost(nn.Module):
    """``Σ_t (x_t - x*)ᵀ diag(q) (x_t - x*) + u_tᵀ diag(r) u_t`` with the terminal state weight
    ``terminal_factor · diag(q)``, as a cost module ``forward(obs) -> QuadraticCost``.  ``q = exp(log_q)``,
    ``r = exp(log_r)`` (positive; a log scale suits weights spread over decades); the target ``x*`` is a
    parameter with ``learn_target`` and a buffer otherwise."""

    def __init__(self, q: Tensor, r: Tensor, target: Tensor, horizon: int, terminal_factor: float = 10.0,
                 *, learn_target: bool = False):
        super().__init__()
        q, r, target = (torch.as_tensor(v, dtype=torch.float64) for v in (q, r, target))
        if bool((q <= 0).any()) or bool((r <= 0).any()):
            raise ValueError("LearnableQuadraticCost: weights q and r must be positive")
        self.horizon, self.terminal_factor = int(horizon), float(terminal_factor)
        self.log_q = nn.Parameter(q.log())
        self.log_r = nn.Parameter(r.log())
        if learn_target:
            self.target = nn.Parameter(target.clone())
        else:
            self.register_buffer("target", target.clone())

    @property
    def q(self) -> Tensor:
        return self.log_q.exp()

    @property
    def r(self) -> Tensor:
        return self.log_r.exp()

    def forward(self, obs: Tensor | None = None):
        from controllers.costs import QuadraticCost

        T = self.horizon
        Q = torch.diag_embed(self.q)
        Qs = torch.cat([Q.expand(T, *Q.shape), (self.terminal_factor * Q)[None]])
        return QuadraticCost(Q=Qs, R=torch.diag_embed(self.r), x_ref=self.target, check=False)

    def weights(self) -> dict[str, list[float]]:
        """The weights (and their values relative to ``q[0]``) and the target, as plain lists."""
        q, r = self.q.detach(), self.r.detach()
        return {"q": q.tolist(), "r": r.tolist(), "q_rel": (q / q[0]).tolist(), "r_rel": (r / q[0]).tolist(),
                "target": self.target.detach().tolist()}


def expert_cost_weights(task: Task, horizon: int) -> dict[str, Any]:
    """The diagonal weights of ``task.mpc_cost(horizon)``: ``q``, ``r``, ``target``, ``terminal_factor``
    (and ``q_rel``/``r_rel`` relative to ``q[0]``).  Raises ``ValueError`` for a cost that is not a
    :class:`~controllers.costs.QuadraticCost` with diagonal, time-invariant running weights."""
    from controllers.costs import QuadraticCost

    c = task.mpc_cost(horizon, dtype=torch.float64)
    if not isinstance(c, QuadraticCost) or c.N is not None or c.q is not None or c.r is not None:
        raise ValueError(f"train_mpc_cost: {task.name}'s MPC cost is not a diagonal QuadraticCost "
                         f"({type(c).__name__}); only such costs are learned here")
    Q, R = c.Q, c.R
    if Q.dim() != 3 or R.dim() not in (2, 3):
        raise ValueError(f"train_mpc_cost: {task.name}'s MPC cost has batched weights")
    R0 = R if R.dim() == 2 else R[0]
    q = torch.diagonal(Q[0])
    diag_ok = (torch.allclose(Q, torch.diag_embed(torch.diagonal(Q, dim1=-2, dim2=-1)))
               and torch.allclose(R0, torch.diag(torch.diagonal(R0))))
    factor = float((torch.diagonal(Q[-1]) / q).mean())
    if not diag_ok or not torch.allclose(Q[:-1], Q[:1].expand_as(Q[:-1])) \
            or not torch.allclose(torch.diagonal(Q[-1]), factor * q):
        raise ValueError(f"train_mpc_cost: {task.name}'s MPC cost is not diag(q) per step with a terminal "
                         "weight factor·diag(q)")
    r = torch.diagonal(R0)
    target = torch.zeros(task.n, dtype=torch.float64) if c.x_ref is None else c.x_ref.reshape(-1, task.n)[-1]
    return {"q": q.tolist(), "r": r.tolist(), "q_rel": (q / q[0]).tolist(), "r_rel": (r / q[0]).tolist(),
            "target": target.tolist(), "terminal_factor": factor}


def _planning_states(demos: Demos, task: Task, center: Tensor | None,
                     hysteresis: float = math.pi / 2) -> Tensor:
    """The states the expert planned from: ``state_from_obs`` with the angle components on the branch
    :class:`~learning.policies.MPCAdapter` chooses (continued along each episode, with hysteresis)."""
    x = task.state_from_obs(demos.obs).to(torch.float64)
    dims = angle_dims(task) if center is not None else []
    if not dims or len(demos) == 0:
        return x
    mask = torch.zeros(task.n, dtype=torch.bool)
    mask[dims] = True
    c = torch.where(mask, center.to(torch.float64), 0.0)
    two_pi = 2 * math.pi
    out = x.clone()
    prev = torch.full((demos.episodes, task.n), math.nan, dtype=torch.float64)
    for t in range(int(demos.step.max()) + 1):
        rows = torch.nonzero(demos.step == t).flatten()
        if rows.numel() == 0:
            continue
        ep = demos.episode[rows]
        xt = x[rows]
        centered = torch.remainder(xt - c + math.pi, two_pi) - math.pi + c
        p = prev[ep]
        cont = p + torch.remainder(xt - p + math.pi, two_pi) - math.pi
        keep = torch.isfinite(p) & ((cont - c).abs() <= math.pi + hysteresis)
        b = torch.where(mask, torch.where(keep, cont, centered), xt)
        out[rows] = b
        prev[ep] = b
    return out


def _mpc(task: Task, horizon: int, cost: nn.Module, grad: str, max_iter: int):
    from controllers.ilqr import ILQROptions
    from controllers.mpc import MPCPolicy

    umax = torch.tensor(task.u_max(), dtype=torch.float64)
    return MPCPolicy(task.system, horizon, cost, u_lower=-umax, u_upper=umax, grad=grad,
                     options=ILQROptions(max_iter=max_iter))


def mpc_policy(mpc: nn.Module, task: Task | str) -> MPCAdapter:
    """The trained MPC as a :class:`~learning.policies.Policy` for the task (inference: no gradients, the
    same cost module; angles taken around the cost's target as the expert's, warm-started)."""
    task = make_task(task)
    inf = _mpc(task, mpc.horizon, mpc.cost, "none", mpc.options.max_iter if mpc.options else 100)
    return MPCAdapter(inf, task, center=mpc.cost.target.detach())


def _future_plans(demos: Demos, horizon: int, scale: Tensor) -> Tensor:
    """``(S, horizon, m)`` physical controls: for each sample the demo's own actions from its step on
    (``a_t, a_{t+1}, ...``, the episode's last one repeated) — the expert's realized plan."""
    S = len(demos)
    ep = demos.episode
    last = torch.zeros(demos.episodes, dtype=torch.int64).scatter_reduce(
        0, ep, torch.arange(S), reduce="amax", include_self=False)
    idx = torch.minimum(torch.arange(S)[:, None] + torch.arange(horizon)[None], last[ep][:, None])
    return demos.action.to(torch.float64)[idx] * scale


@torch.no_grad()
def mpc_action_mse(mpc: nn.Module, demos: Demos, task: Task | str, *, max_steps: int | None = None,
                   center: Tensor | None = None) -> float:
    """Held-out action MSE of an MPC, *teacher-forced*: the MPC (as :func:`mpc_policy`, warm-starting
    itself from step to step) is fed each demo episode's observations in order — all episodes at once —
    and its normalized actions are compared with the expert's (the first ``max_steps`` steps of each
    episode when given).  An MPC with the expert's cost and solver settings reproduces the expert's
    actions exactly (to rounding); a cold start at each state would not, on a swing-up."""
    task = make_task(task)
    pol = mpc_policy(mpc, task)
    if center is not None:
        pol = MPCAdapter(pol.mpc, task, center=center)
    pol.reset(None)
    E = demos.episodes
    T = int(demos.step.max()) + 1 if len(demos) else 0
    if max_steps is not None:
        T = min(T, int(max_steps))
    row = torch.full((E, T), -1, dtype=torch.int64)
    keep = demos.step < T
    row[demos.episode[keep], demos.step[keep]] = torch.nonzero(keep).flatten()
    obs = demos.obs.to(torch.float64)
    sq, cnt = 0.0, 0
    last = obs[row[:, 0].clamp(min=0)]
    for t in range(T):
        r = row[:, t]
        have = r >= 0
        last = torch.where(have[:, None], obs[r.clamp(min=0)], last)  # an ended episode repeats its last obs
        a = pol.act(last)
        d = (a - demos.action.to(torch.float64)[r.clamp(min=0)]) ** 2
        sq += float(d[have].sum())
        cnt += int(have.sum()) * task.m
    return sq / max(cnt, 1)


def train_mpc_cost(demos: Demos, task: Task | str, horizon: int | None = None, *, steps: int = 60,
                   lr: float = 0.1, batch_size: int = 32, seed: int = 0, init_q=None, init_r=None,
                   learn_target: bool = False, max_iter: int = 20, warm_start: str = "sequential",
                   window: int = 10, seq_steps: int | None = None, val: Demos | None = None,
                   val_refs: bool = True, val_max_steps: int | None = None,
                   eval_every: int = 0) -> tuple[nn.Module, dict[str, Any]]:
    """Learn the MPC's cost weights from the demos by backpropagation through the MPC (module docstring).

    Args:
        demos: training demos of ``task``.
        horizon: planning horizon (default: the expert's, :data:`~learning.policies.DEFAULT_HORIZON`).
        steps: gradient steps (Adam, learning rate ``lr`` on the log-weights).
        init_q, init_r: initial weights (default all ones); the target starts at the expert's and is
            learned only with ``learn_target``.
        max_iter: iLQR iterations per solve (the expert's default is 20).
        warm_start: how the training solves start.  ``"sequential"`` (default): teacher-forced, as the
            expert ran — ``batch_size`` demo episodes at a time are replayed in order (their first
            ``seq_steps`` steps), the MPC cold-started at step 0 and warm-started from its own previous
            plan after, one gradient step per ``window`` control steps (the loss summed over them): the
            expert's cost gives zero loss.  ``"demo"``: minibatches of ``batch_size`` demo states, each
            solve started from the demo's own actions from that step on (weak signal: a solve started
            at the expert's plan tends to stay there whatever the cost).  ``"cold"``: minibatches from
            zero controls (a swing-up expert's own cost does not reproduce its actions that way).
        val: held-out demos: their teacher-forced action MSE (:func:`mpc_action_mse`) after training
            (``val_mse``), and with ``val_refs`` before it (``val_mse_init``) and with the expert's own
            cost (``val_mse_expert_cost``, ~0); every ``eval_every`` steps when positive (``val_curve``).

    Returns:
        ``(mpc, history)``: the trained :class:`~controllers.mpc.MPCPolicy` (``grad="implicit"``; run it
        on the task with :func:`mpc_policy`) and ``{"loss": [...], "nonconverged": [...], "weights_init",
        "weights", "weights_expert", "val_mse"..., "time_s"}``.
    """
    from controllers.mpc import MPCState

    if warm_start not in ("sequential", "demo", "cold"):
        raise ValueError(f"train_mpc_cost: argument 'warm_start' must be 'sequential', 'demo' or 'cold', "
                         f"got {warm_start!r}")
    task = make_task(task)
    H = DEFAULT_HORIZON.get(task.name, 30) if horizon is None else int(horizon)
    expert = expert_cost_weights(task, H)
    n, m = task.n, task.m
    f64 = torch.float64
    q0 = torch.ones(n, dtype=f64) if init_q is None else torch.as_tensor(init_q, dtype=f64)
    r0 = torch.ones(m, dtype=f64) if init_r is None else torch.as_tensor(init_r, dtype=f64)
    target = torch.tensor(expert["target"], dtype=f64)
    cost = LearnableQuadraticCost(q0, r0, target, H, expert["terminal_factor"], learn_target=learn_target)
    mpc = _mpc(task, H, cost, "implicit", max_iter)
    X = _planning_states(demos, task, target)
    A = demos.action.to(f64)
    scale = task.u_scale(f64, "cpu")
    hist: dict[str, Any] = {"loss": [], "nonconverged": [], "val_curve": [], "horizon": H,
                            "warm_start": warm_start, "weights_init": cost.weights(),
                            "weights_expert": expert}

    def val_mse(c: nn.Module) -> float:
        return mpc_action_mse(_mpc(task, H, c, "none", max_iter), val, task, max_steps=val_max_steps,
                              center=target)

    if val is not None and val_refs:
        hist["val_mse_init"] = val_mse(cost)
        hist["val_mse_expert_cost"] = val_mse(LearnableQuadraticCost(
            torch.tensor(expert["q"]), torch.tensor(expert["r"]), target, H, expert["terminal_factor"]))
    opt = torch.optim.Adam(cost.parameters(), lr=lr)
    gen = torch.Generator().manual_seed(seed)
    t0 = time.perf_counter()

    def update(loss: Tensor, conv: Tensor) -> None:
        opt.zero_grad(set_to_none=True)
        if loss.requires_grad:
            loss.backward()
            for p in cost.parameters():
                if p.grad is not None:
                    p.grad.nan_to_num_(0.0, 0.0, 0.0)
            opt.step()
        hist["loss"].append(float(loss.detach()))
        hist["nonconverged"].append(float((~conv).double().mean()))
        k = len(hist["loss"])
        if val is not None and eval_every > 0 and k % eval_every == 0:
            hist["val_curve"].append((k, val_mse(cost)))

    if warm_start == "sequential":
        E = demos.episodes
        T = int(demos.step.max()) + 1
        if seq_steps is not None:
            T = min(T, int(seq_steps))
        row = torch.full((E, T), -1, dtype=torch.int64)
        keep = demos.step < T
        row[demos.episode[keep], demos.step[keep]] = torch.nonzero(keep).flatten()
        while len(hist["loss"]) < steps:
            eps = torch.randperm(E, generator=gen)[:batch_size]
            state = None
            last = row[eps, 0]
            acc, cnt, conv = None, 0, []
            for t in range(T):
                r = row[eps, t]
                have = r >= 0
                last = torch.where(have, r, last)
                u, state = mpc(X[last], state)
                err = ((u / scale - A[last]) ** 2).sum(-1)
                ok = have & torch.isfinite(err)
                e = err[ok].sum()
                acc = e if acc is None else acc + e
                cnt += int(ok.sum()) * m
                conv.append(state.converged[have])
                if (t + 1) % window == 0 or t == T - 1:
                    update(acc / max(cnt, 1), torch.cat(conv))
                    acc, cnt, conv = None, 0, []
                    if len(hist["loss"]) >= steps:
                        break
    else:
        plans = _future_plans(demos, H, scale) if warm_start == "demo" else None
        S = X.shape[0]
        perm, pos = torch.randperm(S, generator=gen), 0
        for _ in range(int(steps)):
            if pos + batch_size > S and pos > 0:
                perm, pos = torch.randperm(S, generator=gen), 0
            b = perm[pos:pos + batch_size]
            pos += b.numel()
            st0 = None
            if plans is not None:
                st0 = MPCState(u=plans[b], converged=torch.zeros(b.numel(), dtype=torch.bool),
                               iterations=torch.zeros(b.numel(), dtype=torch.int64))
            u, st = mpc(X[b], st0)
            err = (u / scale - A[b]) ** 2
            ok = torch.isfinite(err).all(-1)
            update(err[ok].mean(), st.converged)
    hist["time_s"] = time.perf_counter() - t0
    hist["weights"] = cost.weights()
    if val is not None:
        hist["val_mse"] = val_mse(cost)
    return mpc, hist


# ------------------------------------------------------------------------------------------- study
def _eval_record(res) -> dict[str, Any]:
    s = res.summary()
    return {"success_rate": s["success_rate"], "return_mean": s["return"]["mean"],
            "return_std": s["return"]["std"], "final_error_mean": s["final_error"]["mean"],
            "eval_episodes": s["episodes"], "eval_time_s": s["wall_time_s"]}


def _finite(v):
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {k: _finite(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_finite(x) for x in v]
    return v


def bc_study(task: Task | str = "PendulumSwingUp", demo_counts=(1, 2, 5, 10, 20), *, expert: Any = "mpc",
             heldout_episodes: int = 5, seed: int = 0, eval_episodes: int = 16, eval_seed: int = 100_000,
             num_envs: int = 16, learners=("mlp", "mpc"), include_expert: bool = True,
             mlp_kwargs: dict | None = None, mpc_kwargs: dict | None = None, demos: Demos | None = None,
             log=None) -> list[dict[str, Any]]:
    """Behaviour cloning against the number of demonstration episodes (module docstring).

    The demo pool is ``demos`` or ``max(demo_counts) + heldout_episodes`` episodes of ``expert`` from env
    seeds ``seed, seed+1, ...``; the last ``heldout_episodes`` are held out.  Closed-loop evaluation runs
    ``eval_episodes`` episodes from env seeds ``eval_seed, ...`` (disjoint from the demos'), ``num_envs``
    at a time.  ``mlp_kwargs`` / ``mpc_kwargs`` go to :func:`train_mlp_policy` / :func:`train_mpc_cost`.

    Returns a list of JSON-serialisable records, one per (learner, count) — plus one for the expert with
    ``include_expert`` — with keys ``task, learner, demos, train_samples, heldout_mse, train_mse,
    success_rate, return_mean, return_std, final_error_mean, eval_episodes, eval_time_s, train_time_s``
    (and ``weights``, ``weights_expert``, ``heldout_mse_init``, ``heldout_mse_expert_cost`` for the MPC).
    """
    from learning.evaluate import evaluate

    task = make_task(task)
    counts = sorted({int(k) for k in demo_counts})
    say = log if log is not None else (lambda *_: None)
    t0 = time.perf_counter()
    if demos is None:
        demos = collect_demos(expert, task, counts[-1] + heldout_episodes, seed, num_envs=num_envs)
    say(f"demos: {demos.episodes} episodes, {len(demos)} samples, expert success "
        f"{float(demos.success.double().mean()):.2f} ({time.perf_counter() - t0:.1f} s)")
    pool, held = demos.split(heldout_episodes)
    if counts[-1] > pool.episodes:
        raise ValueError(f"bc_study: {counts[-1]} demo episodes asked, the pool has {pool.episodes}")
    ev = dict(num_envs=num_envs, episodes=eval_episodes, seed=eval_seed, progress=False, timing_batch1=False)
    records: list[dict[str, Any]] = []
    base = {"task": task.name, "heldout_episodes": held.episodes, "heldout_samples_total": len(held)}
    if include_expert:
        res = evaluate(expert, task, **ev)
        rec = {**base, "learner": "expert", "demos": None, "train_samples": 0, "heldout_mse": 0.0,
               "train_mse": 0.0, "train_time_s": 0.0, **_eval_record(res)}
        records.append(rec)
        say(f"expert: success {rec['success_rate']:.2f}")
    refs = None  # the MPC's held-out error before training and with the expert's cost (same for every k)
    for k in counts:
        tr = pool.first(k)
        for learner in learners:
            if learner == "mlp":
                kw = dict(mlp_kwargs or {})
                kw.setdefault("seed", seed)
                model, h = train_mlp_policy(tr, **kw)
                dt = h["time_s"]
                rec = {**base, "learner": "mlp", "demos": k, "train_samples": len(tr),
                       "heldout_mse": action_mse(_module_fn(model), held),
                       "train_mse": action_mse(_module_fn(model), tr), "train_time_s": dt}
                pol = model
            elif learner == "mpc":
                kw = dict(mpc_kwargs or {})
                kw.setdefault("seed", seed)
                mpc, h = train_mpc_cost(tr, task, val=held, val_refs=refs is None, **kw)
                if refs is None:
                    refs = {"heldout_mse_init": h["val_mse_init"],
                            "heldout_mse_expert_cost": h["val_mse_expert_cost"]}
                rec = {**base, "learner": "mpc", "demos": k, "train_samples": len(tr),
                       "heldout_mse": h["val_mse"], **refs,
                       "train_mse": float(sum(h["loss"][-5:]) / max(1, len(h["loss"][-5:]))),
                       "train_time_s": h["time_s"], "weights": h["weights"],
                       "weights_expert": h["weights_expert"],
                       "nonconverged_train": float(sum(h["nonconverged"]) / max(1, len(h["nonconverged"])))}
                pol = mpc_policy(mpc, task)
            else:
                raise ValueError(f"bc_study: unknown learner {learner!r} (known: 'mlp', 'mpc')")
            rec.update(_eval_record(evaluate(pol, task, **ev)))
            records.append(_finite(rec))
            say(f"{learner} k={k}: held-out mse {rec['heldout_mse']:.4g}, success {rec['success_rate']:.2f}, "
                f"return {rec['return_mean']:.1f}, train {rec['train_time_s']:.1f} s")
    return records


def format_table(records: list[dict[str, Any]]) -> str:
    """The study's records as a text table."""
    cols = ("learner", "demos", "train_samples", "heldout_mse", "success_rate", "return_mean",
            "train_time_s", "eval_time_s")
    rows = [cols]
    for r in records:
        row = []
        for c in cols:
            v = r.get(c)
            row.append("-" if v is None else (f"{v:.4g}" if isinstance(v, float) else str(v)))
        rows.append(row)
    w = [max(len(r[i]) for r in rows) for i in range(len(cols))]
    return "\n".join("  ".join(f"{v:>{w[i]}}" for i, v in enumerate(r)) for r in rows)


if __name__ == "__main__":  # pragma: no cover - a study from the command line
    import argparse
    import json

    p = argparse.ArgumentParser(description="behaviour cloning study (learning.bc)")
    p.add_argument("--task", default="PendulumSwingUp")
    p.add_argument("--counts", default="1,2,5,10,20")
    p.add_argument("--heldout", type=int, default=5)
    p.add_argument("--eval-episodes", type=int, default=16)
    p.add_argument("--mlp-epochs", type=int, default=200)
    p.add_argument("--mpc-steps", type=int, default=60)
    p.add_argument("--out", default=None)
    a = p.parse_args()
    torch.set_num_threads(1)
    recs = bc_study(a.task, [int(c) for c in a.counts.split(",")], heldout_episodes=a.heldout,
                    eval_episodes=a.eval_episodes, mlp_kwargs={"epochs": a.mlp_epochs},
                    mpc_kwargs={"steps": a.mpc_steps}, log=print)
    print(format_table(recs))
    if a.out:
        with open(a.out, "w") as f:
            json.dump(recs, f, indent=1, allow_nan=False)
