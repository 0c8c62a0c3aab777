"""Everything that acts in the CoNav env, in one place below training and evaluation.

`base` (the observation-only Agent a user writes, the internal StateAgent of the simulator's
privileged agents, and the names of privileged inputs) <- `baselines` (the paper's
scripted Table 2 rows and our oracle planner), `expert` (the imitation teacher), `predictors`
(the intention and trajectory predictors of trained runs), `policy` (the CoNav LSTM policy
stepping in the env, and its agent from a run), `ppo` (a PPO run's agent) <- `registry` (agents
by name or "package.module:factory", as `conav eval` and `conav view` build them). `lift` takes an
agent's weights out as arguments of the rollout that runs it. Training imports the pieces it steps
(expert, policy); evaluation builds agents through the registry.
"""

from conav_jax.envs.agents.base import Agent, StateAgent, row_title

__all__ = ["Agent", "StateAgent", "row_title"]
