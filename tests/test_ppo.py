"""PPO (train/ppo.py): GAE, the clipped loss and the Gaussian log-prob against hand values; the
update pass replays the rollout's log-probs exactly; a short run on the tiny preset under brax's
wrappers checkpoints a policy that ppo_agent loads and evaluate runs; no flax/optax imports."""

import dataclasses
import functools
import json
import math
import re
from pathlib import Path
from types import SimpleNamespace

import brax.envs.base
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs.wrappers import training as brax_training

from conav_jax.checkpoints import (
    checkpoint_path,
    latest_checkpoint,
    load_checkpoint,
    save_checkpoint,
)
from conav_jax.models import policy
from conav_jax.models.policy import PolicyConfig
from conav_jax.optim import adam
from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
from conav_jax.envs.agents.ppo import ppo_agent
from conav_jax.envs.metrics import METRIC_NAMES
from conav_jax.train import ppo
from conav_jax.train.ppo import PPOConfig

# On this 2-core CPU compile time dominates: without LLVM optimisation and XLA's fusion
# emitters the env's graph compiles ~2.5x faster (same results, slower to run, which tiny runs
# do not notice).
FAST = {"xla_backend_optimization_level": 0, "xla_cpu_use_fusion_emitters": False}
jit = functools.partial(jax.jit, compiler_options=FAST)
ROOT = Path(__file__).resolve().parents[1]

# A tiny network at 8x32 panoramas: compile time, not accuracy, is what matters here.
TINY = PolicyConfig(resolution=(8, 32), conv_channels=(4,), conv_kernels=(3,), visual_dim=8,
                    state_dim=8, intention_dim=4, hidden=8)
BLIND = dataclasses.replace(TINY, use_activity=False, use_object=False, use_trajectory=False)


def test_gae_matches_hand_computation_with_a_done_in_the_middle():
    rewards = jnp.array([[1.0], [2.0], [3.0], [4.0]])
    values = jnp.array([[0.5], [1.0], [1.5], [2.0]])
    dones = jnp.array([[0.0], [1.0], [0.0], [0.0]])  # the episode ends with step 1
    adv, ret = ppo.gae(rewards, values, dones, jnp.array([3.0]), gamma=0.9, lam=0.8)
    # t=3: 4 + .9*3 - 2 = 4.7;  t=2: 3 + .9*2 - 1.5 = 3.3, + .72*4.7 = 6.684
    # t=1: done, so 2 - 1 = 1.0 and nothing flows back;  t=0: 1 + .9*1 - .5 = 1.4, + .72*1 = 2.12
    np.testing.assert_allclose(np.asarray(adv)[:, 0], [2.12, 1.0, 6.684, 4.7], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(ret)[:, 0], [2.62, 2.0, 8.184, 6.7], rtol=1e-6)


def test_reset_cycle_covers_the_longest_episode_unless_given():
    assert ppo.resolve_reset_every(PPOConfig(rollout_steps=32), 396).reset_every == 13  # 416 >= 396 steps
    assert ppo.resolve_reset_every(PPOConfig(rollout_steps=128), 128).reset_every == 1
    assert ppo.resolve_reset_every(PPOConfig(rollout_steps=32, reset_every=4), 396).reset_every == 4  # warned
    with pytest.raises(ValueError, match="reset_every must be > 0"):
        PPOConfig(reset_every=0)


def test_clipped_loss_matches_hand_computation():
    cfg = PPOConfig(clip_eps=0.2, value_coef=0.5, entropy_coef=0.01, normalize_advantages=False)
    log_prob = jnp.log(jnp.array([1.5, 0.5, 1.0]))  # ratios against old log-probs of 0
    adv = jnp.array([1.0, -1.0, 2.0])
    loss, aux = ppo.ppo_loss(log_prob, jnp.float32(1.3), jnp.array([1.0, 2.0, 3.0]), jnp.zeros(3), adv,
                             jnp.array([1.5, 2.0, 2.0]), cfg)
    # policy: -mean(min(1.5, 1.2), min(-0.5, -0.8), 2) = -0.8; value: 0.5 * mean(.25, 0, 1)
    assert aux["policy_loss"] == pytest.approx(-0.8, rel=1e-6)
    assert aux["value_loss"] == pytest.approx(0.5 * 1.25 / 3, rel=1e-6)
    assert float(loss) == pytest.approx(-0.8 + 0.5 * 0.5 * 1.25 / 3 - 0.01 * 1.3, rel=1e-6)
    assert aux["clip_frac"] == pytest.approx(2 / 3)
    kl = np.mean([0.5 - math.log(1.5), -0.5 - math.log(0.5), 0.0])
    assert aux["approx_kl"] == pytest.approx(kl, rel=1e-5)

    normalised, _ = ppo.ppo_loss(log_prob, 0.0, jnp.zeros(3), jnp.zeros(3), adv, jnp.zeros(3),
                                 dataclasses.replace(cfg, normalize_advantages=True, value_coef=0.0))
    z = (np.asarray(adv) - np.mean(adv)) / (np.std(adv) + 1e-8)
    r = np.array([1.5, 0.5, 1.0])
    assert float(normalised) == pytest.approx(-np.mean(np.minimum(r * z, np.clip(r, 0.8, 1.2) * z)), rel=1e-5)


def test_gaussian_log_prob_matches_the_formula():
    a, m, log_std = np.array([0.3, -0.2]), np.array([0.1, 0.4]), np.array([-0.5, 0.2])
    s = np.exp(log_std)
    hand = sum(-((a - m) ** 2) / (2 * s**2) - np.log(s * math.sqrt(2 * math.pi)))
    got = ppo.gaussian_log_prob(jnp.asarray(a), jnp.asarray(m), jnp.asarray(log_std))
    assert float(got) == pytest.approx(hand, rel=1e-6)
    entropy = sum(0.5 * np.log(2 * math.pi * math.e * s**2))
    assert float(ppo.gaussian_entropy(jnp.asarray(log_std))) == pytest.approx(entropy, rel=1e-6)


class CountdownEnv(brax.envs.base.Env):
    """A stand-in brax env with the policy's observation keys (8x32 rgbd): episodes of 2-5
    steps, observations that change every step, so a carry that leaks across an episode
    boundary or starts from the wrong state changes the replayed outputs."""

    def reset(self, rng):
        ps = jnp.stack([0.0, jax.random.randint(rng, (), 2, 6).astype(jnp.float32)])  # (t, length)
        zero = jnp.zeros(())
        return brax.envs.base.State(ps, self._obs(ps), zero, zero, {"reached": zero, "collided": zero}, {})

    def step(self, state, action):
        ps = state.pipeline_state.at[0].add(1.0)
        done = (ps[0] >= ps[1]).astype(jnp.float32)
        reward = -jnp.sum(jnp.square(action - 0.3))
        return state.replace(pipeline_state=ps, obs=self._obs(ps), reward=reward, done=done,
                             metrics={"reached": done, "collided": jnp.zeros(())})

    @staticmethod
    def _obs(ps):
        t, length = ps[0], ps[1]
        ramp = jnp.linspace(0.0, 1.0, 8 * 32 * 4).reshape(8, 32, 4)
        return {"rgbd": jnp.sin(3.0 * ramp * (t + 1.0)), "gps_compass": jnp.stack([t, length, 0.1 * t]),
                "human_pos": jnp.stack([length - t, 1.0])}

    @property
    def observation_size(self):
        return {"rgbd": (8, 32, 4), "gps_compass": (3,), "human_pos": (2,)}

    @property
    def action_size(self):
        return 2

    @property
    def backend(self):
        return "countdown"


@pytest.mark.parametrize("recurrent", [True, False])
def test_update_pass_replays_the_rollout_log_probs(recurrent):
    b, t = 3, 6
    env = brax_training.wrap(CountdownEnv(), episode_length=100)
    params = policy.init(jax.random.PRNGKey(0), BLIND)
    params["log_std"] = jnp.array([-1.0, -0.3])

    reset = jit(lambda key: ppo.EnvCarry(env.reset(jax.random.split(key, b)), policy.initial_carry(BLIND, b),
                                         jnp.ones((b,), bool), jnp.zeros((b,), bool)))
    roll = jit(lambda params, start, key: ppo.rollout(env, BLIND, recurrent, params, start, key, t))
    start = reset(jax.random.PRNGKey(0))
    mid, _, _, stats = roll(params, start, jax.random.PRNGKey(1))
    _, traj, _, stats2 = roll(params, mid, jax.random.PRNGKey(2))  # starts mid-episode, non-zero carry
    # Every slot's first episode (2-5 steps) ends in the first 6 steps; the auto-reset replays
    # it and it ends again by step 10, which the stats must not count.
    assert int(stats["episodes"]) == int(stats["reached"]) == b and int(stats2["episodes"]) == 0
    assert np.asarray(mid.ended).all()
    carry = mid.carry
    assert traj.first.any() and not traj.first.all()  # episodes start inside the segment
    mb = {"obs": traj.obs, "first": traj.first, "action": traj.action, "carry": carry}
    if not recurrent:  # feed-forward minibatches are flat samples
        mb = {k: jax.tree.map(lambda x: x.reshape(b * t, *x.shape[2:]), v) for k, v in mb.items() if k != "carry"}
        mb["log_prob"] = traj.log_prob.reshape(-1)
    replay = jit(ppo.evaluate_actions, static_argnums=(1, 2))
    log_prob, _, value = replay(params, BLIND, recurrent, mb)
    np.testing.assert_allclose(np.asarray(log_prob).reshape(t, b), np.asarray(traj.log_prob), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(np.asarray(value).reshape(t, b), np.asarray(traj.value), rtol=1e-5, atol=1e-5)
    if recurrent:  # the test can tell: a zero start carry replays differently
        mb["carry"] = policy.initial_carry(BLIND, b)
        assert not np.allclose(np.asarray(replay(params, BLIND, recurrent, mb)[2]), np.asarray(traj.value), atol=1e-6)
        return

    # One feed-forward update: epochs x minibatches over the T*B steps, finite, params move.
    cfg = PPOConfig(num_envs=b, rollout_steps=t, epochs=2, minibatches=2, recurrent=False)
    adv, ret = ppo.gae(traj.reward, traj.value, traj.done, jnp.zeros(b), cfg.gamma, cfg.gae_lambda)
    opt = adam(1e-2)
    upd = jit(lambda p, s, k: ppo.update(p, s, traj, carry, adv, ret, k, BLIND, cfg, opt))
    new, opt_state, metrics = upd(params, opt.init(params), jax.random.PRNGKey(2))
    assert int(opt_state.step) == cfg.epochs * cfg.minibatches
    assert all(np.isfinite(float(v)) for v in metrics.values())
    assert not np.allclose(np.asarray(new["value_head"]["w"]), np.asarray(params["value_head"]["w"]))


def _imitation_run(path, config=TINY):
    """A stand-in for a `conav train policy` run dir (train/policy.py's config layout)."""
    params = policy.init(jax.random.PRNGKey(5), config)
    run_config = {"kind": "policy", "model": dataclasses.asdict(config)}
    save_checkpoint(checkpoint_path(path, 10), params=params, opt_state=None, config=run_config, step=10)
    return params


def test_init_from_loads_the_imitation_policy_and_rejects_bad_runs(tmp_path):
    params = _imitation_run(tmp_path / "bc")
    loaded, config = ppo.load_policy_init(tmp_path / "bc")
    assert config == TINY
    jax.tree.map(np.testing.assert_array_equal, loaded, params)
    with pytest.raises(ValueError, match="has its own network config"):  # caught before any env is built
        ppo.train_ppo_from_data(tmp_path / "no_data", tmp_path / "rl", PPOConfig(), PolicyConfig(resolution=(16, 64)), init_from=tmp_path / "bc")
    with pytest.raises(FileNotFoundError, match="not found"):
        ppo.load_policy_init(tmp_path / "missing")
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        ppo_agent(None, tmp_path)
    with pytest.raises(ValueError, match="'policy' run, expected 'ppo'"):
        ppo_agent(None, tmp_path / "bc")
    # A PPO run's checkpoint (same layout) against an env rendering another resolution.
    save_checkpoint(checkpoint_path(tmp_path / "rl8x32", 1), params=params, opt_state=None, step=1,
                    config={"kind": "ppo", "model": dataclasses.asdict(TINY), "ppo": dataclasses.asdict(PPOConfig())})
    wide = SimpleNamespace(config=EnvConfig(sensor=SensorConfig(resolution=(8, 64))))
    with pytest.raises(ValueError, match="trained on 8x32 panoramas but the env renders 8x64"):
        ppo_agent(wide, tmp_path / "rl8x32", ground_truth=True)
    # PPO trains on ground-truth intentions; evaluated, it reads predictors or says it was given the truth.
    with pytest.raises(ValueError, match="pass intention_run \\(or ground_truth=True"):
        ppo_agent(wide, tmp_path / "rl8x32")


def test_short_run_on_tiny_preset_checkpoints_a_policy_that_evaluates(tmp_path, tiny_data, monkeypatch):
    bc = _imitation_run(tmp_path / "bc")
    options = []  # each evaluator's compiler options
    real_evaluator = ppo.make_evaluator
    monkeypatch.setattr(ppo, "make_evaluator", lambda *a, **k: options.append(k.get("compiler_options")) or real_evaluator(*a, **k))
    # 3 iterations of 4 envs x 32 steps; validation once, at the end (iteration 3).
    cfg = PPOConfig(num_envs=4, rollout_steps=32, total_env_steps=384, epochs=2, minibatches=2,
                    reset_every=2, eval_every=3, ckpt_every=2, recurrent=True)
    result = ppo.train_ppo_from_data(tiny_data, tmp_path / "rl", cfg, init_from=tmp_path / "bc",
                                     progress=False, compiler_options=FAST)
    assert result.env_steps == 384 and result.policy_config == TINY
    assert not np.allclose(np.asarray(result.params["value_head"]["w"]), np.asarray(bc["value_head"]["w"]))

    records = [json.loads(line) for line in (tmp_path / "rl" / "log.jsonl").read_text().splitlines()]
    train = [r for r in records if r["split"] == "train"]
    assert [r["env_steps"] for r in train] == [128, 256, 384]
    assert all(np.isfinite(r["loss"]) and r["steps_per_s"] > 0 for r in train)
    (val,) = [r for r in records if r["split"] == "minival"]  # evaluated on minival, never on val
    assert set(METRIC_NAMES) <= set(val)
    assert val == {"step": 3, "env_steps": 384, "split": "minival", "intention_source": "ground_truth", **result.val}
    assert options == [FAST]  # the validation's rollout compiles as the run's updates do

    last = latest_checkpoint(tmp_path / "rl")
    assert last == checkpoint_path(tmp_path / "rl", 3)
    ckpt = load_checkpoint(last)
    assert ckpt.config["kind"] == "ppo" and ckpt.config["ppo"]["recurrent"] is True
    assert ckpt.config["model"]["resolution"] == [8, 32] and ckpt.extra["val"] == result.val
    assert ckpt.config["env"]["data_dir"] == str(tiny_data)  # the train env's dataset
    jax.tree.map(np.testing.assert_array_equal, ckpt.params, result.params)

    # The validation above is ppo_agent(val env, this run dir, ground truth) run through
    # envs.rollout.evaluate (one compile of the val rollout; a second would double this test's time).
    val_env = ConavEnv(str(tiny_data), "val", EnvConfig(sensor=SensorConfig(resolution=(8, 32))))
    agent = ppo_agent(val_env, tmp_path / "rl", ground_truth=True)
    assert agent.name == "ppo" and agent.intention_source == "ground_truth" and "ground-truth intentions" in agent.privileged


def test_no_flax_or_optax_imports_in_our_packages():
    pattern = re.compile(r"^\s*(import|from)\s+(flax|optax)\b", re.M)
    offenders = [str(p.relative_to(ROOT)) for pkg in ("conav_jax", "envs", "train", "eval")
                 for p in sorted((ROOT / pkg).rglob("*.py")) if pattern.search(p.read_text())]
    assert offenders == []
