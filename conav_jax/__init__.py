"""conav_jax: data side of the CoNav benchmark (scenes, activities, motion, episodes, planning)
and the pure-JAX learning stack (nn, models, optim, checkpoints).

Data flows one way: `conav_jax` <- `envs` (MJX simulator, sensors) <- `train`, `eval`.
Nothing in this package imports `envs`, `train` or `eval`.
"""

__version__ = "0.1.0"
