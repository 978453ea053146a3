"""Stateless torch envs: reset/step as pure functions of (state, action, params), any batch
shape and device, differentiable rollouts (issue 6; TorchRL's Pendulum tutorial)."""

from relayrl.envs.stateless.adapter import STATELESS_ENVS, StatelessBatchEnv, StatelessGymEnv, make_batch_env
from relayrl.envs.stateless.base import (
    Obs,
    ObsSpec,
    StatelessEnv,
    StepResult,
    bounded,
    make_generator,
    tree_leaves,
    tree_map,
    tree_where,
)
from relayrl.envs.stateless.check import SpecError, check_env
from relayrl.envs.stateless.pendulum import (
    Pendulum,
    PendulumParams,
    PendulumState,
    make_pendulum,
    pendulum_params,
    pendulum_transforms,
)
from relayrl.envs.stateless.rollout import Rollout, rollout
from relayrl.envs.stateless.transforms import (
    Cat,
    Cos,
    ObservationNorm,
    RescaleAction,
    RewardScale,
    RunningObservationNorm,
    Select,
    Sin,
    Transform,
    TransformedEnv,
    Unsqueeze,
)

__all__ = [
    "Cat", "Cos", "Obs", "ObsSpec", "ObservationNorm", "Pendulum",
    "PendulumParams", "PendulumState", "RescaleAction", "RewardScale", "Rollout", "RunningObservationNorm",
    "STATELESS_ENVS", "Select", "Sin", "SpecError", "StatelessBatchEnv", "StatelessEnv", "StatelessGymEnv",
    "StepResult", "Transform", "TransformedEnv", "Unsqueeze", "bounded", "check_env", "make_batch_env",
    "make_generator", "make_pendulum", "pendulum_params",
    "pendulum_transforms", "rollout", "tree_leaves", "tree_map", "tree_where",
]
