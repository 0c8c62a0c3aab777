"""conav_jax: a batched simulator and benchmark for CoNav, human-centred collaborative navigation.

Evaluate your own agent::

    import conav_jax

    env = conav_jax.make_env("data/tiny", split="val", resolution=(112, 448))
    agent = conav_jax.Agent("my agent", init, act)   # init(key, obs) -> carry
                                                      # act(carry, obs, key) -> (carry, (v_lin, v_ang))
    results = conav_jax.evaluate(env, agent, seed=0)  # results.summary["FASR"]: value and 95% interval

The public names (loaded on first use, so `import conav_jax.data` stays light):

- `make_env(data_dir, split="val", resolution=(112, 448), **EnvConfig fields) -> ConavEnv`,
  a brax `Env` (conav_jax.envs).
- `Agent(title, init, act, reads=None, privileged=())`: an agent that sees observations only,
  jittable, for one environment; `reads` the observation keys it gets (default: every sensor),
  `privileged` the privileged inputs it declares (`PRIVILEGED_INPUTS`), which its results row
  names.
- `evaluate(env, agent, batch=256, seed=0, episodes=None, out_dir=None) -> Results`: every
  episode once; per-episode records, the summary with 95% intervals, and with `out_dir` the
  CSV, metrics.json and report.md that `conav eval` writes.
- `OBSERVATIONS`: the observation table (key, shape, dtype, units, frame, privileged input);
  `observation_shapes(env.config)` its shapes for an env. Privileged keys reach only agents
  that declare their privileged input.

Trainers take envs and configs, and write a run directory (checkpoints, log.jsonl) that the
agents load: `conav_jax.train.live.train_live(env, policy_config, live_config, out_dir, intention,
trajectory)` (the CoNav policy imitating the expert live; `train_live_seeds(env, policy_config,
live_configs, out_dirs, ...)` trains several seeds of one configuration as one program),
`train.policy.train_policy`,
`train.intention.train_intention`, `train.trajectory.train_trajectory`,
`train.goalnav.train_objectnav` / `train_imagenav` and `train.ppo.train_ppo` (each `(train_env,
val_env, run_dir, config, ...)`), `train.goalnav.train_objectnav_live(env, model, live_config,
out_dir)` (the object-goal baseline imitating its planner live); each has a `..._from_data(data_dir, ...)` twin that builds the
envs as the `conav train` command does.

The package itself holds the data side (scenes, activities, motion, episodes, planning) and
the pure-JAX learning stack (nn, models, optim, checkpoints). Data flows one way: `conav_jax`
<- `conav_jax.envs` (MJX simulator, sensors) <- `conav_jax.train`, `conav_jax.eval`; only the
lazy names above reach upwards, when they are used.
"""

import importlib

__version__ = "0.1.0"

_PUBLIC = {
    "make_env": "conav_jax.eval.api",
    "evaluate": "conav_jax.eval.api",
    "Results": "conav_jax.eval.api",
    "Agent": "conav_jax.envs.agents.base",
    "PRIVILEGED_INPUTS": "conav_jax.envs.agents.base",
    "ConavEnv": "conav_jax.envs",
    "OBSERVATIONS": "conav_jax.envs.observations",
    "observation_shapes": "conav_jax.envs.observations",
}
__all__ = sorted(_PUBLIC)


def __getattr__(name: str):
    if name in _PUBLIC:
        return getattr(importlib.import_module(_PUBLIC[name]), name)
    raise AttributeError(f"module 'conav_jax' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_PUBLIC))
