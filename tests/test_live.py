"""train.live in the hand-built hall (8x32 panoramas, a tiny policy): with beta = 1 the lanes
drive as the expert's own rollout does, every label is the expert's action on the state it
was taken in, a pass of the queue runs every train episode once, in an order fixed by the seed
alone, a killed run resumes bit for bit, and its run directory loads as the CoNav agent."""

import dataclasses
import functools
import json
import re
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from worlds import make_split

from conav_jax.checkpoints import checkpoint_path
from conav_jax.models import policy
from conav_jax.models.policy import PolicyConfig
from conav_jax.nav.expert import initial_carry
from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
from conav_jax.envs.agents.expert import expert_agent, make_expert_step
from conav_jax.envs.agents.policy import load_policy_run, policy_agent
from conav_jax.envs.mjcf import UD
from conav_jax.envs.rollout import make_param_rollout
from conav_jax.train import live as lv
from conav_jax.train.live import LiveConfig

SMALL = EnvConfig(sensor=SensorConfig(resolution=(8, 32)), end_at_reach=True)  # as training runs it
TINY = PolicyConfig(resolution=(8, 32), conv_channels=(4,), conv_kernels=(3,), visual_dim=8, state_dim=8,
                    intention_dim=4, hidden=8)
BLIND = dataclasses.replace(TINY, use_activity=False, use_object=False, use_trajectory=False)
STARTS = [(2.5, 2.0, 0.0), (7.5, 3.0, np.pi), (5.0, 1.0, 0.5), (3.0, 3.0, 0.0), (6.0, 2.5, -1.0)]
# Iteration 0 is behaviour cloning (beta 1), iteration 1 mixes (beta 0.5), then the learner alone.
LIVE = LiveConfig(lanes=3, window_steps=12, iterations=4, lr=1e-2, warmup_iterations=0, beta_start=1.0,
                  beta_end=0.0, beta_decay_iterations=2, seed=3, ckpt_every=2, log_every=1)
# On this 2-core CPU compile time dominates: without LLVM optimisation and XLA's fusion emitters
# the env's graph compiles several times faster. train_live's own compile, shared by the tests.
FAST = {"xla_backend_optimization_level": 0, "xla_cpu_use_fusion_emitters": False}
OPTIONS = tuple(sorted(FAST.items()))
WINDOWS = 8  # iterations the queue tests run: more than one pass of the five episodes


@pytest.fixture(scope="module")
def hall():
    env = ConavEnv(episodes=make_split(STARTS), config=SMALL)
    return SimpleNamespace(env=env, num=len(STARTS))


def _windows(env, config, iterations=WINDOWS):
    """`iterations` iterations of `config` from the start, compiled as train_live compiles them
    -> (their steps, host, each (T, N, ...) stacked over iterations on axis 0, the last state)."""
    fns, iteration = lv.make_iteration(env, config, LIVE, compiler_options=OPTIONS)
    state = fns.init(policy.init(jax.random.PRNGKey(LIVE.seed), config))
    windows = []
    for k in range(iterations):
        state, metrics = iteration(state, lv.iteration_key(LIVE.seed, k))
        windows.append(jax.device_get(metrics[lv.STEPS]))
    return jax.tree.map(lambda *xs: np.stack(xs), *windows), state


@pytest.fixture(scope="module")
def tiny(hall):
    return _windows(hall.env, TINY)


def _started(window) -> tuple[np.ndarray, np.ndarray]:
    """(queue positions, episodes) of the episodes the windows started, by position."""
    first = window.first
    pos, ep = window.position[first], window.episode[first]
    order = np.argsort(pos, kind="stable")
    return pos[order], ep[order]


def test_behaviour_cloning_drives_as_the_expert_rollout(hall, tiny):
    window, _ = tiny
    w0 = jax.tree.map(lambda x: x[0], window)  # iteration 0: beta 1
    assert w0.expert_acted.all() and w0.first[0].all()
    steps = LIVE.window_steps
    rollout = make_param_rollout(hall.env, lambda _: expert_agent(hall.env), steps, record=True, compiler_options=FAST)
    _, trace = rollout(None, jax.random.PRNGKey(0), jnp.asarray(w0.episode[0]))
    for lane in range(LIVE.lanes):
        # Each lane runs its first episode from step 0 until it ends or the window does.
        n = int(np.argmax(w0.first[1:, lane])) + 1 if w0.first[1:, lane].any() else steps
        assert n > 3 and (w0.episode[:n, lane] == w0.episode[0, lane]).all()
        np.testing.assert_array_equal(w0.t[:n, lane], np.arange(n))
        np.testing.assert_array_equal(w0.pose[0, lane], STARTS[w0.episode[0, lane]])
        # The pose before step t + 1 is the expert rollout's pose after its step t.
        np.testing.assert_allclose(w0.pose[1:n, lane], np.asarray(trace.robot_pose)[lane, : n - 1], atol=1e-5)
        np.testing.assert_allclose(w0.label[: n - 1, lane], np.asarray(trace.action)[lane, : n - 1], atol=1e-6)


def test_labels_are_the_expert_action_on_the_visited_states(hall, tiny):
    window, _ = tiny
    assert 0.2 < window.expert_acted[1].mean() < 0.8 and not window.expert_acted[2:].any()  # beta 0.5, then 0
    expert = make_expert_step(hall.env)

    @jax.jit
    def label(episode, t, pose, carry):
        ud = jnp.zeros(len(UD)).at[UD["t"]].set(t.astype(jnp.float32))
        state = SimpleNamespace(info={"episode": episode}, pipeline_state=SimpleNamespace(qpos=pose, userdata=ud))
        return expert(state, carry)

    flat = jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), window)  # (iterations * T, N, ...)
    checked = 0
    for lane in range(LIVE.lanes):
        carry = initial_carry()
        for s in range(flat.t.shape[0]):
            if flat.first[s, lane]:
                carry = initial_carry()
            got, carry = label(flat.episode[s, lane], flat.t[s, lane], flat.pose[s, lane], carry)
            np.testing.assert_allclose(flat.label[s, lane], got, atol=1e-6)
            checked += not flat.expert_acted[s, lane]
    assert checked > 20  # states the learner drove to


def test_a_pass_runs_every_train_episode_once(hall, tiny):
    window, state = tiny
    pos, ep = _started(window)
    np.testing.assert_array_equal(pos, np.arange(len(pos)))  # each position handed out once, in order
    assert len(pos) > hall.num and int(state.cursor) == len(pos)
    assert sorted(ep[: hall.num]) == list(range(hall.num))  # pass 0: every episode, none twice
    np.testing.assert_array_equal(ep, np.asarray(lv.episodes_at(LIVE.seed, jnp.asarray(pos), hall.num)))
    # More lanes than episodes: twelve positions from 3 span passes 0 to 3.
    passes = np.concatenate([np.asarray(lv.pass_permutation(LIVE.seed, p, hall.num)) for p in range(4)])
    np.testing.assert_array_equal(lv.episodes_at(LIVE.seed, jnp.arange(3, 15), hall.num), passes[3:15])


def test_paired_seeds_share_the_episode_order_across_ablations(hall, tiny):
    blind, _ = _windows(hall.env, BLIND, iterations=4)
    pos, ep = _started(tiny[0])
    bpos, bep = _started(blind)
    np.testing.assert_array_equal(bep, ep[: len(bep)])
    assert len(bpos) > hall.num  # into the second pass
    orders = [np.asarray(lv.pass_permutation(seed, p, 20)) for seed in (LIVE.seed, LIVE.seed + 1) for p in (0, 1)]
    assert all(sorted(o) == list(range(20)) for o in orders)
    assert len({tuple(o) for o in orders}) == 4  # passes and seeds draw their own orders


def test_seeds_share_one_compiled_iteration_and_keep_their_own_queue(hall, tiny):
    """Every seed of a configuration runs the one compiled program (the seed is in the state):
    seed 3's lanes (LIVE.seed, `tiny`) still start seed 3's episodes, and another seed's init
    starts its own."""
    _, compiled = lv.make_iteration(hall.env, TINY, LIVE, compiler_options=OPTIONS)
    other = dataclasses.replace(LIVE, seed=LIVE.seed + 1)
    fns, same = lv.make_iteration(hall.env, TINY, other, compiler_options=OPTIONS)
    assert same is compiled
    state = fns.init(policy.init(jax.random.PRNGKey(other.seed), TINY))
    assert int(state.seed) == other.seed
    state, metrics = same(state, lv.iteration_key(other.seed, 0))
    steps = jax.device_get(metrics[lv.STEPS])
    first = steps.first[0]  # every lane starts at step 0, on queue positions 0..N-1
    np.testing.assert_array_equal(steps.episode[0][first],
                                  np.asarray(lv.episodes_at(other.seed, jnp.arange(LIVE.lanes), hall.num)))
    assert not np.array_equal(lv.episodes_at(other.seed, jnp.arange(hall.num), hall.num),
                              lv.episodes_at(LIVE.seed, jnp.arange(hall.num), hall.num))


def test_the_log_tells_a_policy_that_ignores_its_inputs_by_its_action_spread(hall):
    """A policy whose action is one constant (its head's weights zero: the mean-action collapse)
    logs an action spread of 0 (to rounding) beside the labels' spread; the freshly drawn policy's is above 0.
    The spreads are of the window the update trained on, BC (beta 1: the expert drove)."""
    fns, compiled = lv.make_iteration(hall.env, TINY, LIVE, compiler_options=OPTIONS)
    params = policy.init(jax.random.PRNGKey(LIVE.seed), TINY)
    head = params["action_head"]
    constant = {**params, "action_head": {"w": jnp.zeros_like(head["w"]), "b": jnp.full_like(head["b"], 0.3)}}
    spreads = []
    for p in (params, constant):
        _, metrics = compiled(fns.init(p), lv.iteration_key(LIVE.seed, 0))
        spreads.append((float(metrics["action_spread"]), float(metrics["label_spread"])))
    (fresh, label), (collapsed, same_label) = spreads
    assert collapsed < 1e-6 < 1e-4 < fresh and label == same_label > 0.1
    labels = jax.device_get(_windows(hall.env, TINY, iterations=1)[0].label[0])  # (T, N, 2)
    np.testing.assert_allclose(label, labels.reshape(-1, 2).std(axis=0).mean(), rtol=1e-5)


@pytest.fixture(scope="module")
def run(hall, tmp_path_factory):
    out = tmp_path_factory.mktemp("live") / "run"
    result = lv.train_live(hall.env, TINY, LIVE, out, progress=False, compiler_options=FAST)
    return SimpleNamespace(dir=out, result=result)


def test_killed_run_resumes_bit_for_bit(hall, run):
    full = jax.device_get(run.result.state)
    log = [json.loads(line) for line in (run.dir / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log] == [1, 2, 3, 4]
    assert log[0]["beta"] == 1.0 and log[0]["expert_share"] == 1.0 and log[2]["expert_share"] == 0.0
    assert all(np.isfinite(r["loss"]) and r["env_steps"] == r["step"] * 36 for r in log)
    # kill -9 after iteration 3, in the middle of writing the checkpoint of iteration 4: the
    # last whole checkpoint is iteration 2's, a temp file lies beside it, the log runs on.
    checkpoint_path(run.dir, 4).unlink()
    (run.dir / ".ckpt_00000004.npz.tmp-1-deadbeef").write_bytes(b"PK\x03")
    resumed = lv.train_live(hall.env, TINY, dataclasses.replace(LIVE, log_every=2), run.dir, progress=False,
                            compiler_options=FAST)
    for a, b in zip(jax.tree.leaves(full), jax.tree.leaves(jax.device_get(resumed.state)), strict=True):
        np.testing.assert_array_equal(a, b)
    assert [json.loads(line)["step"] for line in (run.dir / "log.jsonl").read_text().splitlines()] == [1, 2, 4]
    # The last checkpoint keeps the weights and Adam's state, not the lanes: a finished run run
    # again returns them, and trains no more.
    with np.load(checkpoint_path(run.dir, 4)) as last, np.load(checkpoint_path(run.dir, 2)) as middle:
        assert len(last.files) < len(middle.files) and last.files == [f for f in middle.files if f in last.files]
    again = lv.train_live(hall.env, TINY, LIVE, run.dir, progress=False, compiler_options=FAST)
    assert int(again.state.iteration) == LIVE.iterations and again.env_steps == resumed.env_steps
    for a, b in zip(jax.tree.leaves((full.params, full.opt_state)), jax.tree.leaves((again.state.params, again.state.opt_state)),
                    strict=True):
        np.testing.assert_array_equal(a, b)
    assert len((run.dir / "log.jsonl").read_text().splitlines()) == 3
    with pytest.raises(ValueError, match="cannot resume .* live.lr"):
        lv.train_live(hall.env, TINY, dataclasses.replace(LIVE, lr=1e-3), run.dir, compiler_options=FAST)


def _assert_same_run(lone, together, exact: bool) -> None:
    """Two TrainStates of one seed (but their window scratch, which is not state): their
    counters, episodes and lanes' integer state equal, their floats equal (`exact`) or within
    float32 rounding of a batched program's other sum order."""
    lone, together = (jax.device_get(st._replace(window_obs={})) for st in (lone, together))
    for a, b in zip(jax.tree.leaves(lone), jax.tree.leaves(together), strict=True):
        a, b = np.asarray(a), np.asarray(b)
        if exact or not np.issubdtype(a.dtype, np.floating):
            np.testing.assert_array_equal(a, b)
        else:
            np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)


def test_seeds_trained_together_are_the_runs_trained_alone_and_resume_together(hall, run, tmp_path):
    five = dataclasses.replace(LIVE, seed=5)
    alone = lv.train_live(hall.env, TINY, five, tmp_path / "alone5", progress=False, compiler_options=FAST)
    dirs = [tmp_path / "s3", tmp_path / "s5"]
    three, also_five = lv.train_live_seeds(hall.env, TINY, [LIVE, five], dirs, progress=False, compiler_options=FAST)
    _assert_same_run(run.result.state, three.state, exact=False)
    _assert_same_run(alone.state, also_five.state, exact=False)
    assert [int(r.state.seed) for r in (three, also_five)] == [3, 5] and three.env_steps == run.result.env_steps
    # Each directory is a run of its own seed, logged and checkpointed as a lone run is.
    for d, seed in zip(dirs, (3, 5)):
        assert load_policy_run(d)[2]["live"]["seed"] == seed
        assert [json.loads(line)["step"] for line in (d / "log.jsonl").read_text().splitlines()] == [1, 2, 3, 4]
    log, lone = ([json.loads(line) for line in (d / "log.jsonl").read_text().splitlines()]
                 for d in (dirs[1], tmp_path / "alone5"))
    assert [r["episodes_started"] for r in log] == [r["episodes_started"] for r in lone]
    np.testing.assert_allclose([r["loss"] for r in log], [r["loss"] for r in lone], rtol=1e-4)
    # Killed in the middle of iteration 4's checkpoints: both resume from iteration 2, together,
    # to the weights they had.
    for d in dirs:
        checkpoint_path(d, 4).unlink()
    again = lv.train_live_seeds(hall.env, TINY, [LIVE, five], dirs, progress=False, compiler_options=FAST)
    _assert_same_run(three.state, again[0].state, exact=True)
    _assert_same_run(also_five.state, again[1].state, exact=True)
    checkpoint_path(dirs[1], 4).unlink()
    with pytest.raises(ValueError, match=r"different iterations \[2, 4\]"):
        lv.train_live_seeds(hall.env, TINY, [LIVE, five], dirs, progress=False, compiler_options=FAST)
    with pytest.raises(ValueError, match="differ in lr, not only in seed"):
        lv.train_live_seeds(hall.env, TINY, [LIVE, dataclasses.replace(five, lr=1.0)], dirs, compiler_options=FAST)
    with pytest.raises(ValueError, match="repeated seeds"):
        lv.train_live_seeds(hall.env, TINY, [LIVE, LIVE], dirs, compiler_options=FAST)


def test_seeds_trained_together_keep_a_lone_runs_skips(hall):
    """The refill's reset of ended lanes and the learner's turn under beta = 1 run only when
    needed (conds): vmapped over runs, a cond whose predicate differs by run would become both
    branches for every lane, so the runs take those choices together. And each run's
    convolutions are a lone run's, not one grouped convolution of all runs."""
    state = lv.make_live(hall.env, TINY, LIVE).init(policy.init(jax.random.PRNGKey(0), TINY))
    shared = dataclasses.replace(LIVE, seed=0, ckpt_every=1, log_every=1)
    spec = lambda x, lead=(): jax.ShapeDtypeStruct(lead + x.shape, x.dtype)  # noqa: E731
    conds, convolutions = [], []
    for k in (1, 2):
        _, iteration = lv._iteration(hall.env, TINY, shared, None, None, lv.ExpertConfig(), OPTIONS,
                                     *((k,) if k > 1 else ()))
        lead = () if k == 1 else (k,)
        states = lv.TrainState(*(spec(f) if name == "iteration" else jax.tree.map(lambda x: spec(x, lead), f)
                                 for name, f in zip(lv.TrainState._fields, state)))
        text = iteration.lower(states, jax.ShapeDtypeStruct(lead + (2,), jnp.uint32)).as_text()
        conds.append(text.count("stablehlo.case") + text.count("stablehlo.if"))
        convolutions.append(re.findall(r"stablehlo.convolution.*", text))
    assert conds[0] >= 2 and conds[1] == conds[0]
    # Each run's convolutions stay ungrouped (nn.conv: one per run), forward and backward.
    assert convolutions[0] and len(convolutions[1]) == 2 * len(convolutions[0])
    assert not [c for c in convolutions[1] if re.search(r"(feature|batch)_group_count = [2-9]", c)]


def test_run_loads_as_the_conav_agent_and_acts(hall, run):
    params, config, run_config = load_policy_run(run.dir)
    assert config == TINY and run_config["intention_source"] == "ground_truth"
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(run.result.state.params), strict=True):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="ground_truth=True"):  # never reads ground truth unasked
        policy_agent(hall.env, run.dir)
    agent = policy_agent(hall.env, run.dir, ground_truth=True)
    key = jax.random.PRNGKey(0)

    @functools.partial(jax.jit, static_argnums=0)
    def act(agent, params):
        state = hall.env.reset_to_episode(key, 1)
        _, action = agent.act(agent.init(key, state.obs), state.obs, key)
        obs = jax.tree.map(lambda x: x[None], state.obs)
        ref, _, _ = policy.apply(params, TINY, obs, policy.initial_carry(TINY, 1))
        return action, ref[0]

    action, ref = act(agent, params)
    assert action.shape == (2,) and np.isfinite(action).all() and np.abs(action).max() > 1e-4
    np.testing.assert_allclose(action, ref, atol=1e-6)


def test_config_errors_name_the_fields(hall):
    with pytest.raises(ValueError, match="LiveConfig.lanes"):
        LiveConfig(lanes=0)
    with pytest.raises(ValueError, match="LiveConfig.beta_end"):
        LiveConfig(beta_end=1.5)
    with pytest.raises(ValueError, match="exponential"):
        LiveConfig(beta_schedule="exponential", beta_end=0.0)
    with pytest.raises(ValueError, match="SensorConfig\\(resolution=\\(16, 64\\)\\)"):
        lv.make_live(hall.env, dataclasses.replace(TINY, resolution=(16, 64)), LIVE)
    lin = LiveConfig(beta_start=1.0, beta_end=0.2, beta_decay_iterations=4)
    exp = dataclasses.replace(lin, beta_schedule="exponential")
    np.testing.assert_allclose([float(lin.beta(k)) for k in (0, 2, 4, 9)], [1.0, 0.6, 0.2, 0.2], rtol=1e-6)
    np.testing.assert_allclose([float(exp.beta(k)) for k in (0, 2, 4, 9)], [1.0, 0.2**0.5, 0.2, 0.2], rtol=1e-6)


def test_the_initial_state_holds_no_buffer_twice(hall):
    """The compiled iteration donates its state on a GPU, which refuses one buffer given twice:
    every leaf of a fresh TrainState (Adam's two moments, the counters, the seed) is its own."""
    fns = lv.make_live(hall.env, TINY, LIVE)
    leaves = jax.tree.leaves(fns.init(policy.init(jax.random.PRNGKey(0), TINY)))
    assert len({id(x) for x in leaves}) == len(leaves)


def test_the_live_bench_refuses_parts_it_does_not_have_before_building_anything():
    from conav_jax.train.bench import LIVE_PARTS, live_throughput

    assert LIVE_PARTS[-1] == "update" and LIVE_PARTS[:-1] == lv.ROLLOUT_STAGES
    with pytest.raises(ValueError, match="parts must be some of"):
        live_throughput(None, parts=("render",))
    with pytest.raises(ValueError, match="parts must hold 'update'"):
        live_throughput(None, parts=("simulate",), profile_dir="trace")
    with pytest.raises(ValueError, match=r"runs > 1 times the whole iteration alone"):
        live_throughput(None, runs=2)  # runs together: only the whole iteration exists
    with pytest.raises(ValueError, match="runs must be >= 1"):
        live_throughput(None, runs=0, parts=("update",))


def test_benchmarks_report_the_allocators_peak_in_use_where_the_backend_keeps_one(monkeypatch):
    """`peak_bytes_in_use` of every bench (the live one's included) is the allocator's peak of
    bytes in use, not what it reserved; None on a backend that keeps no statistics."""
    from conav_jax.envs import bench

    if jax.default_backend() == "cpu":
        assert bench.peak_memory_bytes() is None

    class Device:
        def memory_stats(self):
            return {"peak_bytes_in_use": 7, "bytes_in_use": 3, "bytes_reserved": 99}

    monkeypatch.setattr(bench.jax, "devices", lambda: [Device()])
    assert bench.peak_memory_bytes() == 7
