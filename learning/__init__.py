"""learning: gymnasium environments (single and natively batched), batched rollout evaluation and RL
baselines built on :mod:`controllers` (see ARCHITECTURE.md).

``import learning`` registers the project's tasks with gymnasium under ``liecontrol/<Name>-v0`` (as gymnasium
1.x packages do; ``gym.register_envs(learning)`` is the idiom that keeps the import from looking unused),
and :func:`register_envs` is idempotent.  Any other gymnasium environment is evaluated by
:func:`evaluate` too, and an MPC acts in it given a model (:mod:`learning.env_models`,
:class:`~learning.model_mpc.ModelMPC`).  stable-baselines3 is
imported only by :mod:`learning.sb3`, :mod:`learning.mpc_policy` and (inside its functions)
:mod:`learning.baselines`, none of which this package imports.
"""

from learning import distributed
from learning.bc import Demos, bc_study, collect_demos, train_mlp_policy, train_mpc_cost
from learning.demos import (
    LETTERS,
    Demonstrations,
    expert_demos,
    handwriting,
    letter_stroke,
    mpc_demos,
    spatial_noise,
    time_warp,
)
from learning.env_models import EnvModel, env_model, register_env_model
from learning.envs import TASKS, CartPoleSwingUp, PendulumSwingUp, Task, TaskEnv
from learning.evaluate import EvalResult, evaluate
from learning.imitation import (
    identifiable_combinations,
    imitation_loss,
    imitation_setup,
    imitation_study,
    learn_dynamics,
)
from learning.ioc import (
    IOCLoss,
    IOCResult,
    LQTCostModel,
    MinimalIntervention,
    SPDWeight,
    ViaPoints,
    fit_cost,
    ioc_loss,
    minimal_intervention,
    normalize_scale,
    time_weights,
)
from learning.manifold_demos import (
    BodyRateSO3,
    ManifoldStatistics,
    MeanTrackingRun,
    manifold_statistics,
    orientation_demos,
    stiffness_demos,
    track_mean,
)
from learning.model_mpc import ModelMPC
from learning.policies import MPCExpert, as_policy, task_expert
from learning.primitives import (
    DMP,
    ProMP,
    Recovery,
    Reproduction,
    Tracking,
    fit_dmp,
    fit_promp,
    integrator_chain,
    perturbation_recovery,
    reproduction_error,
    via_point_error,
)
from learning.registration import env_id, register_envs
from learning.robustness import perturbed_task, robustness_study
from learning.vector import TaskVectorEnv

register_envs()

__all__ = ["Task", "TASKS", "TaskEnv", "TaskVectorEnv", "PendulumSwingUp", "CartPoleSwingUp",
           "register_envs", "env_id", "evaluate", "EvalResult", "as_policy", "MPCExpert", "task_expert",
           "Demos", "collect_demos", "train_mlp_policy", "train_mpc_cost", "bc_study",
           "Demonstrations", "expert_demos", "mpc_demos", "time_warp", "spatial_noise", "handwriting",
           "letter_stroke", "LETTERS", "DMP", "fit_dmp", "Reproduction", "ProMP", "fit_promp", "Tracking",
           "integrator_chain", "reproduction_error", "via_point_error", "perturbation_recovery", "Recovery",
           "SPDWeight", "time_weights", "ViaPoints", "LQTCostModel", "normalize_scale", "IOCLoss", "ioc_loss",
           "IOCResult", "fit_cost", "MinimalIntervention", "minimal_intervention", "orientation_demos",
           "stiffness_demos", "manifold_statistics", "ManifoldStatistics", "BodyRateSO3", "track_mean",
           "MeanTrackingRun", "learn_dynamics", "imitation_study", "imitation_setup", "imitation_loss",
           "identifiable_combinations", "distributed", "perturbed_task", "robustness_study",
           "EnvModel", "env_model", "register_env_model", "ModelMPC"]
