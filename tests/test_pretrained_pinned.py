"""The shipped policy's behaviour, pinned: the CoNav agent with the package's pretrained runs
(policy, intention and trajectory predictors) on a few paper-like val episodes of the `demo`
preset, on this CPU. A change anywhere between the data and the policy's action (episodes,
physics, sensor, predictors, policy, metrics) that moves its outcomes fails here. A deliberate
one updates PINNED and re-measures PROVENANCE.json's val figures at the commit that ships it."""

import dataclasses
import functools
import warnings

import pytest

from conav_jax import pretrained
from conav_jax.data.episodes import BlockedStandingPoint, generate_dataset
from conav_jax.data.presets import preset
from conav_jax.envs import SensorConfig
from conav_jax.envs.agents.policy import policy_agent
from conav_jax.eval import api
from conav_jax.eval.api import evaluate, make_env
from conav_jax.eval.demo import DEMO_PRESET

EPISODES = 4
DEFAULT_EMITTERS = {"xla_cpu_use_fusion_emitters": True}  # XLA's default, set for this test's compiles
# Per val episode: (FASR, RASR, collided before the first reach, AS in steps, t_reach), as
# measured at the commit that added this test (JAX 0.10.2, CPU).
PINNED = [(0, 0, 0, 699, -1), (0, 0, 0, 489, -1), (1, 1, 0, 409, 409), (1, 1, 0, 266, 266)]


@pytest.fixture(scope="module")
def demo_val(tmp_path_factory):
    """One val scene of the demo preset (and the one train episode a dataset needs)."""
    cfg = dataclasses.replace(preset(DEMO_PRESET), train_scenes=1, train_episodes=1, val_scenes=1,
                              val_episodes=EPISODES, minival_scenes=0, minival_episodes=0)
    out = tmp_path_factory.mktemp("demo_val")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BlockedStandingPoint)
        generate_dataset(cfg, out)
    return out


def test_the_shipped_policy_acts_as_pinned(demo_val, monkeypatch):
    # The pins were measured with XLA's default CPU emitters, which tests/conftest.py turns off
    # for the rest of the suite: float rounding, and so these outcomes, depend on them.
    monkeypatch.setattr(api, "make_evaluator", functools.partial(api.make_evaluator, compiler_options=DEFAULT_EMITTERS))
    runs = pretrained.pretrained_runs()
    # The shipped runs were trained on 32x128 panoramas of flat category colours.
    env = make_env(demo_val, "val", resolution=(32, 128), sensor=SensorConfig(materials="flat"))
    agent = policy_agent(env, runs["policy"], runs["intention"], runs.get("trajectory"))
    records = evaluate(env, agent, batch=EPISODES).records
    got = [(r["FASR"], r["RASR"], r["collided_before_reach"], r["AS"], r["t_reach"]) for r in records]
    assert got == PINNED
