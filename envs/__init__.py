"""envs: the MJX CoNav simulator (brax Env) and its sensors. Imports conav_jax only."""
