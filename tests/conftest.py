"""Shared fixtures: one tiny dataset per test session, generated once."""

import os
import sys

import pytest

sys.path.insert(0, os.path.dirname(__file__))  # tests/worlds.py


@pytest.fixture(scope="session")
def tiny_data(tmp_path_factory):
    from conav_jax.episodes import generate_dataset
    from conav_jax.presets import preset

    out = tmp_path_factory.mktemp("tiny")
    generate_dataset(preset("tiny"), out, workers=1)
    return out
