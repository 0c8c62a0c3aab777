"""envs: the MJX CoNav simulator (a brax Env) and its sensors. Imports conav_jax only.

Importing the package registers the environment with brax as 'conav', so
`brax.envs.get_environment('conav', data_dir=..., split=...)` builds it.
"""

import contextlib as _contextlib
import io as _io

# mujoco-mjx prints "Failed to import warp" on import when its optional Warp backend is not
# installed (the JAX physics then runs; PhysicsConfig.impl); keep that line out of every
# command's output.
with _contextlib.redirect_stdout(_io.StringIO()):
    from mujoco import mjx as _mjx  # noqa: F401

from brax import envs as _brax_envs

from conav_jax.envs.conav_env import ConavEnv
from conav_jax.envs.config import EnvConfig, PhysicsConfig, RewardConfig, SensorConfig, run_materials

_brax_envs.register_environment("conav", ConavEnv)

__all__ = ["ConavEnv", "EnvConfig", "PhysicsConfig", "RewardConfig", "SensorConfig", "run_materials"]
