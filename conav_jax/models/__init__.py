"""The CoNav agent's learned models, each `init(key, config) -> params` and
`apply(params, config, ...)` with a frozen dataclass config passed explicitly (static under jit).

perceiver: front-view frames -> next activity / object (long-term intention).
trajectory: past human positions -> next 5 (short-term intention).
policy: panorama, pose, human position, intentions -> velocity action (LSTM).
"""

from conav_jax.models import perceiver, policy, trajectory
from conav_jax.models.perceiver import PerceiverConfig
from conav_jax.models.policy import PolicyConfig, ablation_config
from conav_jax.models.trajectory import TrajectoryConfig

__all__ = [
    "PerceiverConfig",
    "PolicyConfig",
    "TrajectoryConfig",
    "ablation_config",
    "perceiver",
    "policy",
    "trajectory",
]
