"""Control tasks and their gymnasium environments (single env here, the batched one in
:mod:`learning.vector`); every task is defined once, on a :mod:`controllers.systems` model."""

from learning.envs.arm import ArmReach
from learning.envs.bicopter import BicopterHover
from learning.envs.car import CarParking
from learning.envs.cartpole import CartPoleSwingUp
from learning.envs.panda_reach import PandaReach
from learning.envs.pendulum import PendulumSwingUp
from learning.envs.quadrotor import QuadrotorFigureEight, QuadrotorTrack
from learning.envs.single import TaskEnv, make_task
from learning.envs.task import Task, angle_wrap

#: the tasks by registered name
TASKS: dict[str, type[Task]] = {t.name: t for t in (PendulumSwingUp, CartPoleSwingUp, ArmReach, CarParking,
                                                  BicopterHover, QuadrotorTrack, QuadrotorFigureEight,
                                                  PandaReach)}

__all__ = ["Task", "TaskEnv", "make_task", "TASKS", "PendulumSwingUp", "CartPoleSwingUp", "ArmReach",
           "CarParking", "BicopterHover", "QuadrotorTrack", "QuadrotorFigureEight", "PandaReach",
           "angle_wrap"]
