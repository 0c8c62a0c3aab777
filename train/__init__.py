"""train: imitation (intention, trajectory, policy, DAgger) and PPO training loops.

Imports conav_jax and envs; never eval.
"""
