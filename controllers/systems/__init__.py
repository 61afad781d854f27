"""System models: batched dynamics with tensor parameters, shared by MPC, simulators and environments.

Every model is a :class:`controllers.dynamics.System` (a frozen dataclass with ``n``/``m``,
``step(x, u, t)`` (discrete dynamics), ``jacobian(x, u, t) -> (A, B)`` (analytic) and
``time_invariant = True``), with ``derivative(x, u)`` (continuous time) and ``dynamics()`` (the same
model as a :class:`controllers.dynamics.NonlinearDynamics`).  Parameters broadcast against ``x.shape[:-1]``.
The manifold systems (``Quadrotor`` on R³×R³×SO(3), ``UGV`` on a surface × SO(2)) are instead
:class:`controllers.manifold_mpc.ManifoldSystem` s (``x ⊕ Δt f(x, u)``, states are ``ProductState`` s), each
with a simulator that is deliberately not the MPC's model.  :class:`MujocoSystem` is any MuJoCo model (an
``MjModel``, an XML file or a gymnasium MuJoCo env) as a system: ``step`` through ``mujoco.rollout``,
finite-difference Jacobians (needs the ``mujoco`` extra; importing it does not).
"""

from controllers.systems.arm import PlanarArm
from controllers.systems.bicopter import Bicopter
from controllers.systems.car import Car
from controllers.systems.car_velocity import CarVelocity
from controllers.systems.cartpole import CartPole
from controllers.systems.mujoco_system import MujocoSystem
from controllers.systems.panda import JacobianFrame, Panda
from controllers.systems.pendulum import Pendulum
from controllers.systems.quadrotor import Quadrotor, QuadrotorSimulator
from controllers.systems.ugv import UGV, UGVSimulator

__all__ = ["Pendulum", "CartPole", "Car", "CarVelocity", "Bicopter", "PlanarArm", "Panda", "JacobianFrame",
           "Quadrotor", "QuadrotorSimulator", "UGV", "UGVSimulator", "MujocoSystem"]
