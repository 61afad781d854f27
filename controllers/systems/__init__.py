"""System models: batched dynamics with tensor parameters, shared by MPC, simulators and environments.

Every model is a frozen dataclass with ``n``/``m``, ``step(x, u, t)`` (discrete dynamics),
``jacobian(x, u, t) -> (A, B)`` (analytic), ``derivative(x, u)`` (continuous time) and ``dynamics()``
(a :class:`controllers.problem.NonlinearDynamics`).  Parameters broadcast against ``x.shape[:-1]``.
"""

from controllers.systems.cartpole import CartPole
from controllers.systems.pendulum import Pendulum

__all__ = ["Pendulum", "CartPole"]
