"""eval: evaluation sweeps, baselines, reports, rerun viewer, and the `conav` command line.

The top of the import flow: conav_jax <- envs <- train <- eval.
"""
