"""System models: batched dynamics with tensor parameters, shared by MPC, simulators and environments.

Every model is a :class:`controllers.dynamics.System` (a frozen dataclass with ``n``/``m``,
``step(x, u, t)`` (discrete dynamics), ``jacobian(x, u, t) -> (A, B)`` (analytic) and
``time_invariant = True``), with ``derivative(x, u)`` (continuous time) and ``dynamics()`` (the same
model as a :class:`controllers.dynamics.NonlinearDynamics`).  Parameters broadcast against ``x.shape[:-1]``.
"""

from controllers.systems.arm import PlanarArm
from controllers.systems.bicopter import Bicopter
from controllers.systems.car import Car
from controllers.systems.cartpole import CartPole
from controllers.systems.panda import JacobianFrame, Panda
from controllers.systems.pendulum import Pendulum

__all__ = ["Pendulum", "CartPole", "Car", "Bicopter", "PlanarArm", "Panda", "JacobianFrame"]
