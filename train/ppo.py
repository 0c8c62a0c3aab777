"""PPO for the CoNav policy on the brax interface (purejaxrl-style, written by us).

wrapped env (VmapWrapper + EpisodeWrapper + AutoResetWrapper) -> `rollout` (lax.scan over time:
obs, Gaussian actions, log-probs, values, rewards, dones) -> `gae` (reverse scan) -> `update`
(epochs x minibatches, nested scans, `ppo_loss`) -> one jitted `iteration`, driven by a thin
Python loop (`train_ppo`, given the train env and the validation env; `train_ppo_from_data`
builds them from a dataset directory) that logs to RUN/log.jsonl, checkpoints and evaluates on
the validation env.

Choices, stated once:
- Policy: conav_jax.models.policy (the paper's CNN + LSTM), so imitation checkpoints start PPO
  (`init_from`). The feed-forward variant runs the same network from a zero LSTM carry every
  step (the LSTM cell then is a gated dense layer); the recurrent one carries the LSTM state.
- Action distribution: a diagonal Gaussian on the action itself, mean = the policy's tanh
  output, std = exp(params["log_std"]) (state-independent). Log-probs are of the unclipped
  sample; the env clips it to [-1, 1]. The deterministic agent acts with the mean.
- Episode variety: brax's AutoResetWrapper restarts each slot on the episode it was first reset
  to, so every `reset_every` iterations (a cycle) the whole batch is re-reset from fresh keys
  (new episodes). By default a cycle is long enough for the longest episode of the bank, so
  every slot's episode runs to its end (a shorter cycle would never train on the late steps of
  long episodes); the interrupted episodes are bootstrapped from their value like any segment
  end. The logged train episodes (`episodes`, `reach_rate`, `collision_rate`) are each slot's
  first episode of the cycle only: a slot that ends early replays its episode, and counting
  those replays would over-count the short, successful ones.
- Time-limit truncation (EpisodeWrapper) counts as termination; the default episode length is
  longer than any episode of the bank, so only the env's own ends (goal reached, human done).
- Many devices: with a mesh (conav_jax.parallel) the env batch axis (num_envs) of the runner
  is split over the devices, parameters and optimiser state replicated; jit partitions the
  rollout and the update from that.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import brax.envs
import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.wrappers import training as brax_training
from jax.sharding import Mesh
from tqdm import tqdm

import conav_jax.envs  # noqa: F401, I001  (first: registers 'conav' with brax, and imports mjx quietly)
from conav_jax import runs
from conav_jax.checkpoints import checkpoint_path, latest_checkpoint, save_checkpoint
from conav_jax.models import policy
from conav_jax.models.policy import PolicyConfig
from conav_jax.nn.lstm import LSTMState
from conav_jax.optim import Optimizer, adam, clip_by_global_norm
from conav_jax.provenance import PROVENANCE_KEY, provenance
from conav_jax.parallel import batch_sharding, check_divisible, replicated, traced_under
from conav_jax.runs import append_log, finite_or_none
from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
from conav_jax.envs.agents.policy import (
    intention_source,
    load_policy_run,
    policy_agent_from_params,
    policy_inputs,
)
from conav_jax.envs.config import env_settings
from conav_jax.envs.metrics import summarize
from conav_jax.envs.rollout import make_evaluator
from conav_jax.train.env_checks import check_ends_at_reach, check_same_data, check_sensor, check_split

KIND = runs.PPO
LOG_2PI = math.log(2.0 * math.pi)


@dataclass(frozen=True)
class PPOConfig:
    """One PPO run. Steps are env (control) steps of 0.1 s; cadences are in iterations, one
    iteration = `num_envs * rollout_steps` env steps followed by one update."""

    num_envs: int = 64  # B: parallel environments (the explicit batch axis a mesh can shard)
    rollout_steps: int = 128  # T: steps per env per iteration (truncated-BPTT length too)
    total_env_steps: int = 5_000_000  # rounded up to whole iterations
    epochs: int = 4  # passes over each rollout
    minibatches: int = 4  # per epoch; recurrent: over envs (whole sequences), else over steps
    gamma: float = 0.99  # discount per 0.1 s step (horizon ~10 s)
    gae_lambda: float = 0.95
    clip_eps: float = 0.2  # PPO ratio clip
    value_coef: float = 0.5
    entropy_coef: float = 1e-3
    lr: float = 3e-4  # Adam, constant
    max_grad_norm: float = 0.5  # global L2 clip of each minibatch gradient
    normalize_advantages: bool = True  # per minibatch, to zero mean and unit std
    seed: int = 0
    recurrent: bool = True  # LSTM carry through time; False: zero carry every step
    episode_length: int | None = None  # EpisodeWrapper limit; None: longer than every episode
    # Iterations between re-resets of the batch onto new episodes; None: enough for the bank's
    # longest episode, ceil((max_steps + 1) / rollout_steps).
    reset_every: int | None = None
    eval_every: int = 50  # iterations between evaluations (and one at the end); 0: none
    eval_split: str = "minival"  # evaluated on while training; the reported val split stays unseen
    ckpt_every: int = 50  # iterations between checkpoints (one is always written at the end)
    eval_episodes: int | None = None  # first N val episodes; None: all of them
    eval_batch: int = 256  # episodes per evaluation batch

    def __post_init__(self):
        positive = ("num_envs", "rollout_steps", "total_env_steps", "epochs", "minibatches", "reset_every", "eval_batch")
        for name in positive:
            if getattr(self, name) is not None and getattr(self, name) <= 0:
                raise ValueError(f"PPOConfig.{name} must be > 0, got {getattr(self, name)}")
        for name in ("eval_every", "ckpt_every"):
            if getattr(self, name) < 0:
                raise ValueError(f"PPOConfig.{name} must be >= 0, got {getattr(self, name)}")
        for name in ("gamma", "gae_lambda"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"PPOConfig.{name} must be in [0, 1], got {getattr(self, name)}")
        if self.clip_eps <= 0 or self.lr <= 0 or self.max_grad_norm <= 0:
            raise ValueError("PPOConfig needs clip_eps, lr and max_grad_norm > 0")
        if self.value_coef < 0 or self.entropy_coef < 0:
            raise ValueError("PPOConfig needs value_coef and entropy_coef >= 0")
        samples = self.num_envs if self.recurrent else self.num_envs * self.rollout_steps
        if samples % self.minibatches:
            what = "num_envs" if self.recurrent else "num_envs * rollout_steps"
            raise ValueError(f"{what} ({samples}) must be divisible by minibatches ({self.minibatches})")
        if self.episode_length is not None and self.episode_length <= 0:
            raise ValueError(f"PPOConfig.episode_length must be > 0 or None, got {self.episode_length}")
        if self.eval_episodes is not None and self.eval_episodes <= 0:
            raise ValueError(f"PPOConfig.eval_episodes must be > 0 or None, got {self.eval_episodes}")

    @property
    def steps_per_iteration(self) -> int:
        return self.num_envs * self.rollout_steps

    @property
    def num_iterations(self) -> int:
        return -(-self.total_env_steps // self.steps_per_iteration)


# -- the Gaussian policy ---------------------------------------------------------------------------


def gaussian_log_prob(action: jax.Array, mean: jax.Array, log_std: jax.Array) -> jax.Array:
    """log N(action; mean, diag(exp(log_std)^2)) summed over the last axis: `action, mean
    (..., 2)`, `log_std (2,)` -> `(...)`."""
    z = (action - mean) * jnp.exp(-log_std)
    return jnp.sum(-0.5 * jnp.square(z) - log_std - 0.5 * LOG_2PI, axis=-1)


def gaussian_entropy(log_std: jax.Array) -> jax.Array:
    """Entropy (nats) of the diagonal Gaussian, a scalar: sum of log_std + 0.5 log(2 pi e)."""
    return jnp.sum(log_std + 0.5 * (LOG_2PI + 1.0))


def policy_obs(obs: dict, config: PolicyConfig) -> dict:
    """The observations the policy reads (the rollout stores only these): envs.agents.policy's
    policy_inputs (the panorama, pose, human position, the enabled intention inputs and the
    segmentation its saliency channel reads)."""
    return {k: obs[k] for k in policy_inputs(config)}


def evaluate_actions(
    params: dict, policy_config: PolicyConfig, recurrent: bool, mb: dict
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Re-run the policy on stored samples -> `(log_prob, entropy (scalar), value)`, the first
    and last shaped like `mb["action"]` without its last axis.

    Recurrent: `mb` arrays are time-major `(T, b, ...)`, `mb["carry"]` the LSTM carry `(b,
    hidden)` at the segment start and `mb["first"] (T, b)` the episode starts where it is
    zeroed, exactly as the rollout did. Feed-forward: arrays are `(n, ...)`, zero carry."""
    if recurrent:
        obs = jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), mb["obs"])  # (b, T, ...)
        means, values, _ = policy.apply_sequence(params, policy_config, obs, mb["carry"], mb["first"].T)
        means, values = jnp.swapaxes(means, 0, 1), values.T
    else:
        carry = policy.initial_carry(policy_config, mb["action"].shape[0])
        means, values, _ = policy.apply(params, policy_config, mb["obs"], carry)
    log_std = params["log_std"]
    return gaussian_log_prob(mb["action"], means, log_std), gaussian_entropy(log_std), values


# -- rollout ---------------------------------------------------------------------------------------


class EnvCarry(NamedTuple):
    """What passes from one rollout to the next: the wrapped env's batched State, the LSTM
    carry `(B, hidden)` after the last step, and `first (B,)` bool, True where the current
    observation starts an episode (the carry is zeroed before acting on it), and `ended (B,)`
    bool, True where the slot's first episode of the reset cycle has ended (its replays are
    not counted in the stats)."""

    env_state: Any
    carry: LSTMState
    first: jax.Array
    ended: jax.Array


class Transition(NamedTuple):
    """One rollout, time-major `(T, B, ...)`. Step t: the agent saw `obs`, (`first`: an episode
    started there), drew `action` (unclipped) with `log_prob` and critic `value`, then the env
    returned `reward` and `done` (the episode ended with this step)."""

    obs: dict
    first: jax.Array
    action: jax.Array
    log_prob: jax.Array
    value: jax.Array
    reward: jax.Array
    done: jax.Array


def _act(params, policy_config: PolicyConfig, recurrent: bool, obs: dict, carry: LSTMState, first: jax.Array):
    """Policy on a batch: -> (mean (B, 2), value (B,), next carry). Feed-forward keeps a zero carry."""
    if recurrent:
        return policy.apply(params, policy_config, obs, carry, reset=first)
    mean, value, _ = policy.apply(params, policy_config, obs, carry)
    return mean, value, carry


def rollout(
    env, policy_config: PolicyConfig, recurrent: bool, params: dict, start: EnvCarry, key: jax.Array, num_steps: int
) -> tuple[EnvCarry, Transition, jax.Array, dict]:
    """`num_steps` steps of the batched, wrapped env by lax.scan.

    -> `(end EnvCarry, Transition (T, B, ...), last_value (B,) for bootstrapping, stats)`;
    stats sums over the slots whose first episode of the cycle ended in the rollout:
    `episodes`, `return` (their summed reward), `reached`, `collided` (counts)."""

    def step(c: EnvCarry, k):
        obs = policy_obs(c.env_state.obs, policy_config)
        mean, value, carry = _act(params, policy_config, recurrent, obs, c.carry, c.first)
        action = mean + jnp.exp(params["log_std"]) * jax.random.normal(k, mean.shape)
        log_prob = gaussian_log_prob(action, mean, params["log_std"])
        state = env.step(c.env_state, jnp.clip(action, -1.0, 1.0))
        done = state.done > 0
        counted = done & ~c.ended
        stats = {
            "episodes": counted.sum(),
            # The EpisodeWrapper's running sum still holds the whole episode at its last step.
            "return": jnp.where(counted, state.info["episode_metrics"]["sum_reward"], 0.0).sum(),
            "reached": (counted & (state.metrics["reached"] > 0)).sum(),
            "collided": (counted & (state.metrics["collided"] > 0)).sum(),
        }
        tr = Transition(obs, c.first, action, log_prob, value, state.reward, state.done)
        return EnvCarry(state, carry, done, c.ended | done), (tr, stats)

    end, (traj, stats) = jax.lax.scan(step, start, jax.random.split(key, num_steps))
    _, last_value, _ = _act(params, policy_config, recurrent, policy_obs(end.env_state.obs, policy_config),
                            end.carry, end.first)
    return end, traj, last_value, jax.tree.map(jnp.sum, stats)


# -- advantages, loss, update ----------------------------------------------------------------------


def gae(
    rewards: jax.Array, values: jax.Array, dones: jax.Array, last_value: jax.Array, gamma: float, lam: float
) -> tuple[jax.Array, jax.Array]:
    """Generalised advantage estimation by a reverse lax.scan over time.

    `rewards, values, dones (T, B)` (dones[t]: the episode ended with step t, so V(s_{t+1}) is
    not bootstrapped), `last_value (B,)` = V of the observation after step T-1 ->
    `(advantages, returns)` each `(T, B)`, returns = advantages + values (the critic target).
      delta_t = r_t + gamma (1 - d_t) V_{t+1} - V_t,   A_t = delta_t + gamma lam (1 - d_t) A_{t+1}
    """

    def body(nxt, x):
        adv_next, value_next = nxt
        r, v, d = x
        live = 1.0 - d
        delta = r + gamma * live * value_next - v
        adv = delta + gamma * lam * live * adv_next
        return (adv, v), adv

    init = (jnp.zeros_like(last_value), last_value)
    _, adv = jax.lax.scan(body, init, (rewards, values, dones.astype(values.dtype)), reverse=True)
    return adv, adv + values


def ppo_loss(
    log_prob: jax.Array,
    entropy: jax.Array,
    value: jax.Array,
    old_log_prob: jax.Array,
    advantages: jax.Array,
    returns: jax.Array,
    config: PPOConfig,
) -> tuple[jax.Array, dict]:
    """The PPO objective on a minibatch (all arrays the same shape, entropy may be a scalar):
      policy = -mean(min(r A, clip(r, 1 - eps, 1 + eps) A)),  r = exp(log_prob - old_log_prob)
      value  = 0.5 mean((value - returns)^2)
      loss   = policy + value_coef * value - entropy_coef * mean(entropy)
    A is normalised over the minibatch first if `config.normalize_advantages`.
    -> (loss, {policy_loss, value_loss, entropy, approx_kl, clip_frac})."""
    adv = advantages
    if config.normalize_advantages:
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    log_ratio = log_prob - old_log_prob
    ratio = jnp.exp(log_ratio)
    clipped = jnp.clip(ratio, 1.0 - config.clip_eps, 1.0 + config.clip_eps)
    policy_loss = -jnp.mean(jnp.minimum(ratio * adv, clipped * adv))
    value_loss = 0.5 * jnp.mean(jnp.square(value - returns))
    ent = jnp.mean(entropy)
    loss = policy_loss + config.value_coef * value_loss - config.entropy_coef * ent
    aux = {
        "policy_loss": policy_loss,
        "value_loss": value_loss,
        "entropy": ent,
        "approx_kl": jnp.mean(ratio - 1.0 - log_ratio),  # the k3 estimator, >= 0
        "clip_frac": jnp.mean((jnp.abs(ratio - 1.0) > config.clip_eps).astype(jnp.float32)),
    }
    return loss, aux


def loss_fn(params: dict, mb: dict, policy_config: PolicyConfig, config: PPOConfig) -> tuple[jax.Array, dict]:
    """`ppo_loss` of the current params on a minibatch (see `evaluate_actions` for its layout)."""
    log_prob, entropy, value = evaluate_actions(params, policy_config, config.recurrent, mb)
    return ppo_loss(log_prob, entropy, value, mb["log_prob"], mb["advantage"], mb["return"], config)


def _minibatches(samples: dict, key: jax.Array, config: PPOConfig) -> dict:
    """Shuffle and split into `(M, ...)` minibatches. Recurrent: over envs, whole sequences
    kept (`(M, T, B/M, ...)`, carry `(M, B/M, hidden)`); feed-forward: over all T*B steps."""
    m = config.minibatches
    if config.recurrent:
        b = config.num_envs
        idx = jax.random.permutation(key, b).reshape(m, b // m)
        carry = samples.pop("carry")
        out = jax.tree.map(lambda x: jnp.moveaxis(jnp.take(x, idx, axis=1), 1, 0), samples)
        out["carry"] = jax.tree.map(lambda x: jnp.take(x, idx, axis=0), carry)
        return out
    samples = {k: v for k, v in samples.items() if k != "carry"}
    flat = jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), samples)
    n = config.steps_per_iteration
    idx = jax.random.permutation(key, n).reshape(m, n // m)
    return jax.tree.map(lambda x: jnp.take(x, idx, axis=0), flat)


def update(
    params: dict,
    opt_state: Any,
    traj: Transition,
    start_carry: LSTMState,
    advantages: jax.Array,
    returns: jax.Array,
    key: jax.Array,
    policy_config: PolicyConfig,
    config: PPOConfig,
    optimizer: Optimizer,
) -> tuple[dict, Any, dict]:
    """`config.epochs` x `config.minibatches` clipped, Adam steps (nested lax.scans) on one
    rollout. `start_carry (B, hidden)`: the LSTM carry at the rollout's start (recurrent
    minibatches re-run the LSTM from it). -> (params, opt_state, mean of each loss metric and
    of the pre-clip gradient norm over all minibatches)."""
    samples = {
        "obs": traj.obs, "first": traj.first, "action": traj.action, "log_prob": traj.log_prob,
        "advantage": advantages, "return": returns, "carry": start_carry,
    }

    def minibatch_step(state, mb):
        params, opt_state = state
        (loss, aux), grads = jax.value_and_grad(loss_fn, has_aux=True)(params, mb, policy_config, config)
        grads, grad_norm = clip_by_global_norm(grads, config.max_grad_norm)
        params, opt_state = optimizer.update(grads, opt_state, params)
        return (params, opt_state), {"loss": loss, "grad_norm": grad_norm, **aux}

    def epoch(state, k):
        return jax.lax.scan(minibatch_step, state, _minibatches(dict(samples), k, config))

    (params, opt_state), metrics = jax.lax.scan(epoch, (params, opt_state), jax.random.split(key, config.epochs))
    return params, opt_state, jax.tree.map(jnp.mean, metrics)


# -- one training iteration ------------------------------------------------------------------------


class Runner(NamedTuple):
    """Everything one iteration reads and writes (a pytree; `iteration` is an int32 scalar)."""

    params: dict
    opt_state: Any
    env: EnvCarry
    key: jax.Array
    iteration: jax.Array


def env_shardings(tree: Any, mesh: Mesh, num_envs: int) -> Any:
    """Shardings for `tree` on `mesh`: leaves whose leading axis is the env batch `num_envs`
    split over the devices, every other leaf replicated (works on arrays and tracers)."""
    split, whole = batch_sharding(mesh), replicated(mesh)
    return jax.tree.map(lambda x: split if np.ndim(x) and np.shape(x)[0] == num_envs else whole, tree)


def runner_shardings(runner: Runner, mesh: Mesh, num_envs: int) -> Runner:
    """The Runner on a mesh: its env carry split along the env batch, the rest replicated."""
    whole = replicated(mesh)
    return Runner(jax.tree.map(lambda _: whole, runner.params), jax.tree.map(lambda _: whole, runner.opt_state),
                  env_shardings(runner.env, mesh, num_envs), whole, whole)


def resolve_reset_every(config: PPOConfig, episode_length: int) -> PPOConfig:
    """`config` with `reset_every` set: as given, or (None) the fewest iterations in which an
    episode of `episode_length` steps runs to its end. A given cycle shorter than that is
    allowed but warned about: no slot would ever reach the late steps of the longest episodes."""
    cover = -(-episode_length // config.rollout_steps)
    if config.reset_every is None:
        return dataclasses.replace(config, reset_every=cover)
    if config.reset_every < cover:
        print(f"conav train rl: warning: reset_every {config.reset_every} x rollout_steps {config.rollout_steps} = "
              f"{config.reset_every * config.rollout_steps} steps per reset cycle, shorter than the longest "
              f"episode ({episode_length} steps): later steps of long episodes are never trained on", flush=True)
    return config


def make_iteration(env, policy_config: PolicyConfig, config: PPOConfig, mesh: Mesh | None = None):
    """-> `(init_runner(params, key) -> Runner, iteration(runner) -> (runner, metrics))`;
    `iteration` is to be jitted once: it re-resets the batch onto new episodes if
    `iteration % reset_every == 0` (always at iteration 0), then rollout, GAE, update.
    `env` is the wrapped (batched, auto-resetting) brax env.

    The runner from `init_runner` holds a zero placeholder env state of the right shapes
    (`jax.eval_shape`), as iteration 0 resets anyway; both go through one jitted reset, whose
    trace jax caches, so the slow MJX trace happens once. With a `mesh` the start of each
    rollout is constrained to `env_shardings` (envs split over the devices)."""
    if config.reset_every is None:
        raise ValueError("PPOConfig.reset_every is None: resolve it for the env first (resolve_reset_every)")
    optimizer = adam(config.lr)
    reset = jax.jit(env.reset)
    b = config.num_envs

    def fresh(key):
        return EnvCarry(reset(jax.random.split(key, b)), policy.initial_carry(policy_config, b), jnp.ones((b,), bool),
                        jnp.zeros((b,), bool))

    def init_runner(params: dict, key: jax.Array) -> Runner:
        shapes = jax.eval_shape(reset, jax.ShapeDtypeStruct((b, 2), jnp.uint32))
        placeholder = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
        start = EnvCarry(placeholder, policy.initial_carry(policy_config, b), jnp.ones((b,), bool), jnp.zeros((b,), bool))
        return Runner(params, optimizer.init(params), start, key, jnp.zeros((), jnp.int32))

    def iteration(runner: Runner):
        with traced_under(mesh):  # Pallas kernels per device (conav_jax.parallel.lanes_on_devices)
            return _iteration(runner)

    def _iteration(runner: Runner):
        key, k_reset, k_roll, k_update = jax.random.split(runner.key, 4)
        start = jax.lax.cond(runner.iteration % config.reset_every == 0, fresh, lambda _: runner.env, k_reset)
        if mesh is not None:
            start = jax.lax.with_sharding_constraint(start, env_shardings(start, mesh, b))
        end, traj, last_value, stats = rollout(
            env, policy_config, config.recurrent, runner.params, start, k_roll, config.rollout_steps
        )
        adv, ret = gae(traj.reward, traj.value, traj.done, last_value, config.gamma, config.gae_lambda)
        params, opt_state, metrics = update(
            runner.params, runner.opt_state, traj, start.carry, adv, ret, k_update, policy_config, config, optimizer
        )
        metrics = {**metrics, **stats, "reward": traj.reward.mean(), "value": traj.value.mean(),
                   "log_std": params["log_std"].mean()}
        return Runner(params, opt_state, end, key, runner.iteration + 1), metrics

    return init_runner, iteration


# -- agents and checkpoints ------------------------------------------------------------------------


def load_policy_init(run_dir: str | Path) -> tuple[dict, PolicyConfig]:
    """An imitation run's latest policy (actor, value head, log_std) and its PolicyConfig.
    FileNotFoundError / ValueError as envs.agents.policy.load_policy_run raises them."""
    params, policy_config, _ = load_policy_run(run_dir)
    return params, policy_config


# -- the training loop -----------------------------------------------------------------------------


class PPOResult(NamedTuple):
    params: dict
    policy_config: PolicyConfig
    env_steps: int
    val: dict  # the last val metrics (summarize's FASR..AS), {} if none ran
    run_dir: Path


def initial_policy(run_dir: str | Path, config: PPOConfig, policy_config: PolicyConfig | None = None,
                   init_from: str | Path | None = None, mesh: Mesh | None = None) -> tuple[dict, PolicyConfig]:
    """(initial params, PolicyConfig) of a PPO run into `run_dir`: `init_from`'s (an imitation
    "policy" run), else fresh weights of `policy_config` (default PolicyConfig()). ValueError
    for a `run_dir` that holds a checkpoint (PPO runs do not resume), a `policy_config` beside
    `init_from`, or a mesh that does not divide `config.num_envs`; nothing is built or written."""
    if mesh is not None:
        check_divisible(config.num_envs, mesh, "PPOConfig.num_envs")
    if latest_checkpoint(run_dir) is not None:
        raise ValueError(f"{run_dir} already holds a checkpoint; PPO runs do not resume, choose a new run_dir")
    if init_from is None:
        policy_config = policy_config or PolicyConfig()
        return policy.init(jax.random.PRNGKey(config.seed), policy_config), policy_config
    params, loaded = load_policy_init(init_from)
    if policy_config is not None and policy_config != loaded:
        raise ValueError(f"init_from {init_from} has its own network config; do not pass policy_config too")
    return params, loaded


def ppo_env_config(policy_config: PolicyConfig) -> EnvConfig:
    """The config of the envs a PPO run trains and validates in: the policy's resolution, each
    episode ending at the first reach (the reach bonus ends an episode)."""
    h, w = policy_config.resolution
    return EnvConfig(sensor=SensorConfig(resolution=(h, w)), end_at_reach=True)


def train_ppo(
    env: ConavEnv,
    val_env: ConavEnv | None,
    run_dir: str | Path,
    config: PPOConfig = PPOConfig(),
    policy_config: PolicyConfig | None = None,
    init_from: str | Path | None = None,
    progress: bool = True,
    compiler_options: dict | None = None,
    mesh: Mesh | None = None,
) -> PPOResult:
    """Train a PPO policy in `env` (the train split), on its ground-truth intention observations
    (privileged, as imitation trains); log, checkpoint and evaluate (the agent `conav eval
    --agent ppo --ground-truth-intentions` builds) in `val_env` (the split `config.eval_split`
    of the same dataset; unused, and may be None, when `config.eval_every` is 0) into `run_dir`,
    which must hold no checkpoint yet. Both envs as `ppo_env_config` builds them: the policy's
    resolution, one panorama material, episodes ending at the first reach (ValueError naming
    the config field an env does not match, before anything is written). The run records
    `env`'s dataset directory (None for a split made by hand).

    `policy_config`: the network, its resolution included (default: PolicyConfig()); with
    `init_from` (an imitation "policy" run) the network and its weights come from that run.
    `compiler_options` go to `jax.jit`, the validation's rollout's too (tests lower the XLA
    optimisation level). `mesh` (conav_jax.parallel.make_mesh): the envs split over its
    devices, parameters replicated, and the validations' episodes split too (ValueError unless
    `num_envs` divides by the device count)."""
    run_dir = Path(run_dir)
    params, policy_config = initial_policy(run_dir, config, policy_config, init_from, mesh)
    check_split(env.split, "train", "env")
    envs = (("env", env),)
    if config.eval_every:
        if val_env is None:
            raise ValueError(f"PPOConfig.eval_every is {config.eval_every}: give val_env (the "
                             f"{config.eval_split!r} split), or set eval_every=0")
        check_split(val_env.split, config.eval_split, "val_env", "PPOConfig.eval_split")
        check_same_data(env.split, val_env.split)
        envs += (("val_env", val_env),)
    else:
        val_env = None
    for role, e in envs:  # the env renders what the network reads
        check_sensor(e, role, policy_config.resolution, "PolicyConfig.resolution", env.config.sensor.materials,
                     "env's SensorConfig.materials")
        check_ends_at_reach(e, role, "the reach bonus ends an episode")
    episode_length = config.episode_length or env.bank.max_steps + 1
    config = resolve_reset_every(config, min(episode_length, env.bank.max_steps + 1))
    wrapped = brax_training.wrap(env, episode_length=episode_length)
    recurrent = config.recurrent
    evaluator = None if val_env is None else make_evaluator(
        val_env, lambda p: policy_agent_from_params(p, policy_config, name="ppo", recurrent=recurrent),
        config.eval_batch, config.seed, mesh, compiler_options=compiler_options)

    run_dir.mkdir(parents=True, exist_ok=True)
    log_path = run_dir / runs.LOG_FILE
    log_path.unlink(missing_ok=True)  # a log without a checkpoint belongs to no run we can continue
    run_config = {
        "kind": KIND,
        "model": policy.config_dict(policy_config),
        "materials": env.config.sensor.materials,
        "ppo": dataclasses.asdict(config),
        "env": {"episode_length": episode_length, "data_dir": env.split.data_dir,
                "init_from": None if init_from is None else str(init_from)},
        PROVENANCE_KEY: provenance(**env_settings(env.config), encoder=policy.encoder_name(policy_config)),
    }

    init_runner, iteration = make_iteration(wrapped, policy_config, config, mesh)
    runner = init_runner(params, jax.random.PRNGKey(config.seed))
    out_shardings = None
    if mesh is not None:
        placement = runner_shardings(runner, mesh, config.num_envs)
        runner, out_shardings = jax.device_put(runner, placement), (placement, replicated(mesh))
    iteration = jax.jit(iteration, compiler_options=compiler_options, out_shardings=out_shardings)
    n_iter, per_iter = config.num_iterations, config.steps_per_iteration
    val: dict = {}

    def save(it: int) -> None:
        save_checkpoint(checkpoint_path(run_dir, it), params=runner.params, opt_state=runner.opt_state,
                        config=run_config, step=it, extra={"env_steps": it * per_iter, "val": val})

    def validate(it: int) -> None:
        nonlocal val
        episodes = None if config.eval_episodes is None else np.arange(min(config.eval_episodes, val_env.num_episodes))
        # The deterministic agent `conav eval --agent ppo --ground-truth-intentions` builds, on the
        # params just saved; params are an argument of the compiled rollout, so only the first
        # validation compiles.
        val = summarize(evaluator(runner.params, episodes))
        append_log(log_path, {"step": it, "env_steps": it * per_iter, "split": config.eval_split,
                              "intention_source": intention_source(policy_config), **val})

    bar = tqdm(total=n_iter * per_iter, disable=not progress, unit="step", dynamic_ncols=True)
    start = time.perf_counter()
    try:
        for it in range(1, n_iter + 1):
            t0 = time.perf_counter()
            runner, metrics = iteration(runner)
            metrics = {k: float(v) for k, v in metrics.items()}  # the one sync per iteration
            seconds = time.perf_counter() - t0
            episodes = metrics.pop("episodes")
            record = {k: finite_or_none(v) for k, v in metrics.items() if k not in ("return", "reached", "collided")}
            record.update(
                episodes=int(episodes),
                episode_return=finite_or_none(metrics["return"] / episodes) if episodes else None,
                reach_rate=metrics["reached"] / episodes if episodes else None,
                collision_rate=metrics["collided"] / episodes if episodes else None,
                steps_per_s=round(per_iter / seconds, 1),
                elapsed_s=round(time.perf_counter() - start, 2),
                reset_every=config.reset_every,  # conav curve pools the training rates per cycle
            )
            append_log(log_path, {"step": it, "env_steps": it * per_iter, "split": "train", **record})
            if not all(math.isfinite(metrics[k]) for k in ("loss", "grad_norm")):
                raise FloatingPointError(f"non-finite PPO loss or gradient at iteration {it}; see {log_path}")
            bar.set_postfix(steps_s=f"{per_iter / seconds:.0f}", reward=f"{metrics['reward']:.4f}")
            bar.update(per_iter)
            last = it == n_iter
            do_eval = val_env is not None and (it % config.eval_every == 0 or last)
            if do_eval or last or (config.ckpt_every and it % config.ckpt_every == 0):
                save(it)
            if do_eval:
                validate(it)
                save(it)  # again, now with the val metrics in its extra
    finally:
        bar.close()
    return PPOResult(runner.params, policy_config, n_iter * per_iter, val, run_dir)


def train_ppo_from_data(data_dir: str | Path, run_dir: str | Path, config: PPOConfig = PPOConfig(),
                        policy_config: PolicyConfig | None = None, init_from: str | Path | None = None,
                        **kwargs) -> PPOResult:
    """`train_ppo` on the train split of the dataset `data_dir`, validating on
    `config.eval_split` (where `config.eval_every`), its envs as `ppo_env_config` builds them;
    `kwargs` as train_ppo's. The run directory and the network are checked before any env is
    built."""
    _, network = initial_policy(run_dir, config, policy_config, init_from, kwargs.get("mesh"))
    env_config = ppo_env_config(network)
    env = brax.envs.get_environment("conav", data_dir=str(data_dir), split="train", config=env_config)
    val_env = ConavEnv(str(data_dir), config.eval_split, env_config) if config.eval_every else None
    return train_ppo(env, val_env, run_dir, config, policy_config, init_from, **kwargs)
