"""Franka Emika Panda kinematics: pytorch-kinematics on a kinematics-only URDF and a pure-torch DH reference.

The URDF (``controllers/systems/panda_data/panda_kinematics.urdf``, shipped as package data) is written from
Franka's published modified Denavit–Hartenberg (Craig) table ("Robot and interface specifications",
https://frankaemika.github.io/docs/control_parameters.html)::

    joint   a (m)     d (m)    α (rad)   θ
      1     0         0.333    0         q1
      2     0         0        −π/2      q2
      3     0         0.316    π/2       q3
      4     0.0825    0        π/2       q4
      5     −0.0825   0.384    −π/2      q5
      6     0         0        π/2       q6
      7     0.088     0        π/2       q7
   flange   0         0.107    0         0

with ``T_{i−1,i} = RotX(α) TransX(a) RotZ(θ) TransZ(d)``, and the Franka Hand frames of franka_description
after the flange (``panda_hand``: −π/4 about the flange z; ``panda_hand_tcp``: 0.1034 m further along z).

:meth:`Panda.fk` and :meth:`Panda.jacobian` go through pytorch-kinematics (imported lazily, on first use);
:meth:`Panda.fk_dh` is an independent pure-torch product of the same table (no pytorch-kinematics; works
under ``torch.func``), used as the reference in the tests.

Poses are homogeneous matrices ``(*B, 4, 4)`` (torchlie's SE(3) representation); twists are ``[v, ω]``
(torchlie's order — pytorch-kinematics uses the same order).  Three Jacobian frames
(:class:`JacobianFrame`), all ``(*B, 6, 7)`` with ``ξ = J q̇``:

* ``WORLD`` — pytorch-kinematics' default: ``[ṗ, ω]`` in base-frame coordinates, ``ṗ`` the velocity of the
  end-effector origin (also called the hybrid or mixed Jacobian);
* ``BODY`` — ``Ṫ = T · hat(J_b q̇)``: ``J_b = blockdiag(Rᵀ, Rᵀ) J_world`` (torchlie's right/local tangent);
* ``SPATIAL`` — ``Ṫ T⁻¹ = hat(J_s q̇)``: ``J_s = [[I, p̂], [0, I]] J_world`` (torchlie's left/global tangent).

pytorch-kinematics parses URDF origins in float32 (its ``_convert_transform`` builds the rotation from a
float32 rpy tensor), which costs ~2e-8 (measured on 1,000 random q) even in a float64 chain.  So
:func:`_chain` re-reads the joint origins with the standard-library XML parser and gives every joint an
exact float64 offset (through pytorch-kinematics' public ``Frame``/``Joint``/``Transform3d`` objects) before
building the serial chain; pytorch-kinematics' float64 FK then agrees with :meth:`Panda.fk_dh` to ~1e-16.
"""

from __future__ import annotations

import enum
import functools
import math
import threading
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from importlib import resources

import torch
from torch import Tensor

__all__ = ["Panda", "JacobianFrame", "PANDA_DH", "PANDA_Q_MIN", "PANDA_Q_MAX", "PANDA_DQ_MAX", "PANDA_Q_HOME",
           "PANDA_IK_SEEDS"]

#: Franka's modified-DH table: rows ``(a_{i−1}, d_i, α_{i−1})`` for joints 1–7 and the flange (θ = 0).
PANDA_DH: tuple[tuple[float, float, float], ...] = (
    (0.0, 0.333, 0.0),
    (0.0, 0.0, -math.pi / 2),
    (0.0, 0.316, math.pi / 2),
    (0.0825, 0.0, math.pi / 2),
    (-0.0825, 0.384, -math.pi / 2),
    (0.0, 0.0, math.pi / 2),
    (0.088, 0.0, math.pi / 2),
    (0.0, 0.107, 0.0),  # flange
)
#: Franka's published Panda joint position limits (rad) and velocity limits (rad/s).
PANDA_Q_MIN = (-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973)
PANDA_Q_MAX = (2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973)
PANDA_DQ_MAX = (2.1750, 2.1750, 2.1750, 2.1750, 2.6100, 2.6100, 2.6100)
#: The "ready" configuration of franka_ros / libfranka's examples.
PANDA_Q_HOME = (0.0, -math.pi / 4, 0.0, -3 * math.pi / 4, 0.0, math.pi / 2, math.pi / 4)

#: Extra IK starts (for :func:`controllers.ik.solve_ik`'s ``seeds``): greedy picks, among 256 uniform random
#: configurations, of those that solve the most goals on which a start from :data:`PANDA_Q_HOME` fails
#: (3,000 calibration goals = FK of uniform random configurations, generator seed 100; the tests and the
#: benchmark use other goals).  On such goals the first one alone solves 79 %, the first two 93 %.
PANDA_IK_SEEDS = (
    (0.3519, 0.9274, 1.5029, -2.8826, -2.5638, 0.6138, -2.6792),
    (-2.0911, 1.6142, 0.1793, -2.8060, 0.8335, 2.6877, -0.9068),
    (-1.1586, -0.8352, -0.7203, -1.8675, -0.7782, 2.8720, 2.3879),
)

_URDF = "panda_kinematics.urdf"
#: fixed transforms after the flange, per end link: (rotation about z, translation along z)
_TOOLS = {"panda_link8": (0.0, 0.0), "panda_hand": (-math.pi / 4, 0.0),
          "panda_hand_tcp": (-math.pi / 4, 0.1034)}


class JacobianFrame(str, enum.Enum):
    """In which frame :meth:`Panda.jacobian` expresses the end-effector twist ``[v, ω]``."""

    WORLD = "world"  #: [ṗ, ω] in base coordinates, ṗ of the end-effector origin (pytorch-kinematics)
    BODY = "body"  #: Ṫ = T hat(ξ): the twist in the end-effector frame
    SPATIAL = "spatial"  #: Ṫ T⁻¹ = hat(ξ): the twist of the base-frame origin


def urdf_text() -> str:
    """The kinematics-only Panda URDF shipped with the package."""
    return resources.files("controllers.systems").joinpath("panda_data", _URDF).read_text()


def _origin_matrix(joint: ET.Element) -> list[list[float]]:
    """Exact (float64) homogeneous matrix of a URDF joint origin: Trans(xyz) Rz(y) Ry(p) Rx(r)."""
    origin = joint.find("origin")
    xyz = [float(v) for v in origin.get("xyz", "0 0 0").split()] if origin is not None else [0.0] * 3
    r, p, y = [float(v) for v in origin.get("rpy", "0 0 0").split()] if origin is not None else [0.0] * 3
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr, xyz[0]],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr, xyz[1]],
        [-sp, cp * sr, cp * cr, xyz[2]],
        [0.0, 0.0, 0.0, 1.0],
    ]


_BUILD_LOCK = threading.Lock()


@functools.cache
def _chain_cpu64(end_link: str):
    import pytorch_kinematics as pk  # lazy: the import costs seconds (it pulls in matplotlib and scipy)

    text = urdf_text()
    robot = ET.fromstring(text)
    full = pk.build_chain_from_urdf(text)
    full.find_frame(robot.find("link").get("name")).to(dtype=torch.float64, device="cpu")  # the whole tree
    for joint in robot.iter("joint"):
        frame = full.find_frame(joint.find("child").get("link"))
        frame.joint.offset = pk.Transform3d(matrix=torch.tensor(_origin_matrix(joint), dtype=torch.float64))
    return pk.SerialChain(full, end_link, dtype=torch.float64)


@functools.cache
def _chain_cached(end_link: str, dtype: torch.dtype, device: torch.device):
    with _BUILD_LOCK:
        chain = _chain_cpu64(end_link)
        if dtype == torch.float64 and device.type == "cpu":
            return chain
        import copy

        return copy.deepcopy(chain).to(dtype=dtype, device=device)


def _chain(end_link: str, dtype: torch.dtype, device: torch.device):
    """The pytorch-kinematics serial chain for (end link, dtype, device), built once and cached.

    The cache key is the dtype and the normalized device (``torch.device("cuda")`` → ``cuda:0``), never a
    tensor's identity.  Treat the returned chain as read-only.
    """
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", torch.cuda.current_device())
    return _chain_cached(end_link, dtype, device)


def _check_q(q: Tensor, where: str) -> None:
    if not isinstance(q, Tensor) or q.ndim < 1 or q.shape[-1] != 7:
        raise ValueError(f"{where}: q must be a tensor of shape (*B, 7), got "
                         f"{tuple(q.shape) if isinstance(q, Tensor) else type(q).__name__}")
    if not q.is_floating_point():
        raise TypeError(f"{where}: q must be floating point, got {q.dtype}")


def _dh_link(a: float, d: float, alpha: float, theta: Tensor) -> Tensor:
    """``RotX(α) TransX(a) RotZ(θ) TransZ(d)`` for θ ``(*B,)`` -> ``(*B, 4, 4)`` (no in-place ops)."""
    ct, st = torch.cos(theta), torch.sin(theta)
    ca, sa = math.cos(alpha), math.sin(alpha)
    zero, one = torch.zeros_like(theta), torch.ones_like(theta)
    rows = (
        (ct, -st, zero, zero + a),
        (st * ca, ct * ca, zero - sa, zero - sa * d),
        (st * sa, ct * sa, zero + ca, zero + ca * d),
        (zero, zero, zero, one),
    )
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


@dataclass(frozen=True)
class Panda:
    """Franka Emika Panda kinematics (7 revolute joints), batched over any leading dims of ``q (*B, 7)``.

    Attributes:
        end_link: the end-effector frame: ``"panda_link8"`` (the flange, default), ``"panda_hand"`` or
            ``"panda_hand_tcp"`` (Franka Hand, 0.1034 m past the flange).
    """

    end_link: str = "panda_link8"

    dof = 7

    def __post_init__(self):
        if self.end_link not in _TOOLS:
            raise ValueError(f"Panda: end_link must be one of {sorted(_TOOLS)}, got {self.end_link!r}")

    # ------------------------------------------------------------------------------------------ limits
    @staticmethod
    def joint_limits(dtype: torch.dtype | None = None, device=None) -> tuple[Tensor, Tensor]:
        """``(q_min (7,), q_max (7,))``: Franka's published Panda position limits (rad)."""
        return (torch.tensor(PANDA_Q_MIN, dtype=dtype, device=device),
                torch.tensor(PANDA_Q_MAX, dtype=dtype, device=device))

    @staticmethod
    def velocity_limits(dtype: torch.dtype | None = None, device=None) -> Tensor:
        """``dq_max (7,)``: Franka's published Panda joint velocity limits (rad/s)."""
        return torch.tensor(PANDA_DQ_MAX, dtype=dtype, device=device)

    @staticmethod
    def home(dtype: torch.dtype | None = None, device=None) -> Tensor:
        """The "ready" configuration ``(0, −π/4, 0, −3π/4, 0, π/2, π/4)`` as a ``(7,)`` tensor."""
        return torch.tensor(PANDA_Q_HOME, dtype=dtype, device=device)

    @staticmethod
    def ik_seeds(dtype: torch.dtype | None = None, device=None) -> Tensor:
        """:data:`PANDA_IK_SEEDS` ``(3, 7)``: extra starts for :func:`controllers.ik.solve_ik`."""
        return torch.tensor(PANDA_IK_SEEDS, dtype=dtype, device=device)

    @staticmethod
    def random_q(n: int | tuple[int, ...], generator: torch.Generator | None = None,
                 dtype: torch.dtype | None = None, device=None) -> Tensor:
        """``(*n, 7)`` joint configurations uniform inside the position limits."""
        shape = (n,) if isinstance(n, int) else tuple(n)
        if device is None and generator is not None:
            device = generator.device
        lo, hi = Panda.joint_limits(dtype, device)
        u = torch.rand(*shape, 7, generator=generator, dtype=lo.dtype, device=device)
        return lo + u * (hi - lo)

    # ------------------------------------------------------------------------------------------ kinematics
    def chain(self, dtype: torch.dtype = torch.float64, device=None):
        """The (cached, read-only) pytorch-kinematics ``SerialChain`` for this end link, dtype and device."""
        return _chain(self.end_link, dtype, torch.device(device if device is not None else "cpu"))

    def fk(self, q: Tensor) -> Tensor:
        """End-effector pose ``(*B, 4, 4)`` in the base frame (pytorch-kinematics)."""
        _check_q(q, "Panda.fk")
        batch = q.shape[:-1]
        flat = q.reshape(-1, 7)
        if flat.shape[0] == 0:
            return q.new_zeros(*batch, 4, 4)
        chain = self.chain(q.dtype, q.device)
        T = chain.forward_kinematics_tensor(flat)[chain.frame_to_idx[self.end_link]]
        return T.reshape(*batch, 4, 4)

    def fk_and_jacobian(self, q: Tensor, frame: JacobianFrame | str = JacobianFrame.WORLD
                        ) -> tuple[Tensor, Tensor]:
        """``(T (*B, 4, 4), J (*B, 6, 7))`` from one pytorch-kinematics pass; ``J`` in ``frame``."""
        _check_q(q, "Panda.fk_and_jacobian")
        frame = JacobianFrame(frame)
        batch = q.shape[:-1]
        flat = q.reshape(-1, 7)
        if flat.shape[0] == 0:
            return q.new_zeros(*batch, 4, 4), q.new_zeros(*batch, 6, 7)
        chain = self.chain(q.dtype, q.device)
        J, T = chain.jacobian_tensor(flat, ret_eef_pose=True)
        J = _convert_jacobian(J, T, frame)
        return T.reshape(*batch, 4, 4), J.reshape(*batch, 6, 7)

    def jacobian(self, q: Tensor, frame: JacobianFrame | str = JacobianFrame.WORLD) -> Tensor:
        """Geometric Jacobian ``(*B, 6, 7)``: end-effector twist ``[v, ω] = J q̇`` (see the module doc)."""
        return self.fk_and_jacobian(q, frame)[1]

    def fk_dh(self, q: Tensor) -> Tensor:
        """Pure-torch forward kinematics ``(*B, 4, 4)`` from :data:`PANDA_DH` (no pytorch-kinematics).

        Built from stacks and matmuls only (no in-place writes), so ``torch.func.jacrev``/``vmap`` and
        autograd go through it.
        """
        _check_q(q, "Panda.fk_dh")
        T = None
        for i, (a, d, alpha) in enumerate(PANDA_DH):
            theta = q[..., i] if i < 7 else torch.zeros_like(q[..., 0])
            Ti = _dh_link(a, d, alpha, theta)
            T = Ti if T is None else T @ Ti
        yaw, dz = _TOOLS[self.end_link]
        if yaw != 0.0 or dz != 0.0:
            T = T @ _dh_link(0.0, dz, 0.0, torch.full_like(q[..., 0], yaw))
        return T


def _convert_jacobian(J: Tensor, T: Tensor, frame: JacobianFrame) -> Tensor:
    if frame is JacobianFrame.WORLD:
        return J
    if frame is JacobianFrame.BODY:
        Rt = T[..., :3, :3].transpose(-1, -2)
        return torch.cat((Rt @ J[..., :3, :], Rt @ J[..., 3:, :]), -2)
    # spatial: v_s = ṗ − ω × p = ṗ + p × ω
    p = T[..., :3, 3].unsqueeze(-1).expand_as(J[..., 3:, :])
    v = J[..., :3, :] + torch.linalg.cross(p, J[..., 3:, :], dim=-2)
    return torch.cat((v, J[..., 3:, :]), -2)
