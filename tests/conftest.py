"""Shared fixtures: one tiny dataset per test session, generated once."""

import os
import sys

# Compile-time, not run-time, dominates this suite on a 2-core CPU: XLA's cheapest backend
# optimisation level and its older CPU emitters (no fusion emitters) compile several times
# faster; float rounding may differ from the defaults' (tests that pin numbers allow for it).
# Set before JAX initialises its backend.
_FAST_FLAGS = " --xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false"
os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + _FAST_FLAGS).strip()
# Commands run by the tests compile afresh and write nothing under the user's cache directory.
os.environ["CONAV_COMPILE_CACHE"] = "off"

import pytest  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))  # tests/worlds.py


@pytest.fixture(scope="session")
def tiny_data(tmp_path_factory):
    import warnings

    from conav_jax.data.episodes import BlockedStandingPoint, generate_dataset
    from conav_jax.data.presets import preset

    out = tmp_path_factory.mktemp("tiny")
    with warnings.catch_warnings():  # the tiny preset drops a carpet or two: tests/test_episodes.py checks it
        warnings.simplefilter("ignore", BlockedStandingPoint)
        generate_dataset(preset("tiny"), out, workers=1)
    return out


@pytest.fixture(scope="session")
def runs_32x128():
    """{"policy", "intention", "trajectory": run directory}: a CoNav policy trained on the paper
    preset at 32x128 on flat category colours, reading every intention input, with the two
    predictors it reads (parameters only; their PROVENANCE is results/paper's DAgger seed 0), for
    tests that need a trained policy with predictors."""
    from pathlib import Path

    root = Path(__file__).resolve().parent / "runs_32x128"
    return {name: root / name for name in ("policy", "intention", "trajectory")}
