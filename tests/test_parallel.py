"""Data parallelism (conav_jax.parallel): sharded runs over 4 (forced host) devices give the
losses, metrics and recorded windows of single-device runs; the mesh helpers fail with clear messages.

XLA fixes the host device count when jax starts, and this test session has started it, so the
4-device runs happen in one child process (this file run as a script), which prints its results
as JSON for the tests here to check.
"""

import json
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
DEVICES = 4
FAST = {"xla_backend_optimization_level": 0}


# -- the child process -------------------------------------------------------------------------


def _loop_losses(tmp: Path, mesh) -> dict:
    """train.loop.train of a tiny linear model whose loss also draws per-sample noise from its
    key, 4 updates logged one by one."""
    import jax
    import jax.numpy as jnp

    from conav_jax.runs import read_log
    from conav_jax.train.loop import TrainConfig, train

    rng = np.random.default_rng(0)
    data = {"x": rng.normal(size=(32, 3)).astype(np.float32), "y": rng.normal(size=(32, 2)).astype(np.float32)}
    params = {"w": jnp.zeros((3, 2)), "b": jnp.zeros((2,))}
    cfg = TrainConfig(steps=4, batch=8, lr=0.05, warmup_steps=0, log_every=1, val_every=100, ckpt_every=100)
    result = train(tmp / ("single" if mesh is None else "sharded"), _linear_loss, params, data, cfg, {"kind": "test"},
                   progress=False, compiler_options=FAST, mesh=mesh)
    losses = [r["loss"] for r in read_log(result.run_dir) if r.get("split") == "train"]
    return {"losses": losses, "w": np.asarray(result.params["w"]).tolist(),
            "param_devices": len(result.params["w"].sharding.device_set)}


def _linear_loss(params, batch, key):
    import jax
    import jax.numpy as jnp

    noise = 0.01 * jax.random.normal(key, batch["y"].shape)
    err = batch["x"] @ params["w"] + params["b"] + noise - batch["y"]
    return jnp.mean(jnp.square(err)), {}


def _evaluate_metrics(mesh) -> dict:
    """envs.rollout.evaluate of the random agent (its actions come from the per-episode keys)
    on 5 hall episodes in batches of 3 (the second padded), 8x32 panoramas. One agent only:
    each env rollout compiles for ~25 s here."""
    from worlds import make_split

    from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
    from conav_jax.envs.agents.registry import make_agent
    from conav_jax.envs.rollout import evaluate

    split = make_split([(2.5, 2.0, 0.0), (7.5, 3.0, np.pi), (5.0, 1.0, 1.0), (3.0, 3.0, -1.0), (8.0, 1.5, 2.0)])
    env = ConavEnv(episodes=split, config=EnvConfig(sensor=SensorConfig(resolution=(8, 32))))
    m = evaluate(env, make_agent("random", env), batch=3, seed=1, mesh=mesh)
    return {k: np.asarray(v).tolist() for k, v in m.items()}


def _policy_updates(mesh) -> dict:
    """Two BC updates (train.loop's single-update mode, as `conav train policy` runs on a CPU)
    on synthetic windows (a tiny policy)."""
    import jax

    from conav_jax.models import policy
    from conav_jax.models.policy import PolicyConfig
    from conav_jax.parallel import replicate
    from conav_jax.train.imitation import bc_loss
    from conav_jax.train.loop import TrainConfig, make_optimizer, make_single, make_update

    pcfg = PolicyConfig(resolution=(8, 32), conv_channels=(4,), conv_kernels=(3,), visual_dim=8, state_dim=8,
                        intention_dim=4, hidden=8)
    n, w = 16, 4
    rng = np.random.default_rng(1)
    obs = {
        "rgb": rng.integers(0, 256, (n, w, 8, 32, 3), dtype=np.uint8),
        "depth": rng.uniform(0, 5, (n, w, 8, 32)).astype(np.float16),
        "segmentation": rng.integers(-1, pcfg.num_objects, (n, w, 8, 32)).astype(np.int8),
        "gps_compass": rng.normal(size=(n, w, 3)).astype(np.float32),
        "human_pos": rng.normal(size=(n, w, 2)).astype(np.float32),
        "activity_probs": rng.dirichlet(np.ones(pcfg.num_activities), (n, w)).astype(np.float32),
        "object_probs": rng.dirichlet(np.ones(pcfg.num_objects), (n, w)).astype(np.float32),
        "future_traj": rng.normal(size=(n, w, pcfg.horizon, 2)).astype(np.float32),
    }
    reset = np.zeros((n, w), bool)
    reset[:, 0] = True
    data = {"obs": obs, "label": rng.uniform(-1, 1, (n, w, 2)).astype(np.float32),
            "mask": np.ones((n, w), np.float32), "reset": reset}
    cfg = TrainConfig(batch=8, lr=1e-2, warmup_steps=0)
    params = policy.init(jax.random.PRNGKey(0), pcfg)
    optimizer = make_optimizer(cfg)
    opt_state = optimizer.init(params)
    place = jax.device_put if mesh is None else lambda t: replicate(t, mesh)
    params, opt_state, data = place((params, opt_state, data))
    update = make_update(lambda p, b, k: bc_loss(p, pcfg, b), optimizer, cfg, n, mesh)
    single = jax.jit(make_single(update, cfg.batch), compiler_options=FAST)
    sums = {"loss": 0.0, "grad_norm": 0.0, "steps_in_loss": 0.0, "lr": 0.0, "n": 0}
    carry, losses = (params, opt_state, np.int32(-1), np.zeros(cfg.batch, np.int32), sums), []
    for _ in range(2):
        before = float(carry[4]["loss"])
        carry = single(carry[0], carry[1], data, *carry[2:])
        losses.append(float(carry[4]["loss"]) - before)
    return {"losses": losses, "grad_norm_sum": float(carry[4]["grad_norm"]), "bad": int(carry[2]),
            "params": [float(np.asarray(x).sum()) for x in jax.tree.leaves(carry[0])]}


def _recording(mesh) -> dict:
    """train.imitation.record_windows of the expert on the 5 hall episodes in batches of 3 (the
    second padded), 8x32 panoramas, a tiny policy: the windows kept, summed leaf by leaf, and
    how many programs `advance` compiled."""
    import jax
    from worlds import make_split

    from conav_jax.models import policy
    from conav_jax.models.policy import PolicyConfig
    from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
    from conav_jax.train import imitation as im

    pcfg = PolicyConfig(resolution=(8, 32), conv_channels=(4,), conv_kernels=(3,), visual_dim=8, state_dim=8,
                        intention_dim=4, hidden=8)
    split = make_split([(2.5, 2.0, 0.0), (7.5, 3.0, np.pi), (5.0, 1.0, 1.0), (3.0, 3.0, -1.0), (8.0, 1.5, 2.0)])
    env = ConavEnv(episodes=split, config=EnvConfig(sensor=SensorConfig(resolution=(8, 32)), end_at_reach=True))
    rec = im.make_recorder(env, pcfg, seq_len=16, burn_in=8)
    advance = jax.jit(rec.advance)
    m, windows, steps = im.record_windows(rec, jax.jit(rec.start), advance,
                                          policy.init(jax.random.PRNGKey(0), pcfg), jax.random.PRNGKey(2),
                                          np.arange(5), 1.0, batch=3, mesh=mesh)
    return {"windows": len(windows["label"]), "steps": steps, "t_reach": np.asarray(m["t_reach"]).tolist(),
            "sums": [float(np.asarray(x, np.float64).sum()) for x in jax.tree.leaves(windows)],
            "advance_compiles": advance._cache_size()}


def _env_steps(mesh) -> dict:
    """envs.bench.step_lanes: 3 env steps of 8 hall lanes through the Pallas caster (interpreted
    on the CPU), per lane; with a mesh each device steps and casts its own 2 lanes."""
    import jax
    import jax.numpy as jnp
    from worlds import make_split

    from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
    from conav_jax.envs.bench import step_lanes

    split = make_split([(2.5, 2.0, 0.0), (7.5, 3.0, np.pi), (5.0, 1.0, 1.0), (3.0, 3.0, -1.0)])
    env = ConavEnv(episodes=split, config=EnvConfig(sensor=SensorConfig(resolution=(8, 32), kind="pallas",
                                                                        pallas_interpret=True)))
    run = step_lanes(env, 3, mesh)
    out = run(jax.random.split(jax.random.PRNGKey(3), 8), jnp.arange(8) % 4)
    return {"lanes": np.asarray(out).tolist(), "devices": len(out.sharding.device_set)}


def _pallas_partitioned(mesh) -> dict:
    """Instance-coloured panoramas of 8 hall lanes from the Pallas caster (interpreted on the
    CPU) inside one program XLA partitions over the mesh (envs.rollout.jit_with_bank under it):
    each device casts its own lanes (conav_jax.parallel.lanes_on_devices)."""
    import jax
    import jax.numpy as jnp
    from worlds import make_split

    from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
    from conav_jax.envs.rollout import jit_with_bank
    from conav_jax.parallel import constrain_batch, shard_batch

    split = make_split([(2.5, 2.0, 0.0), (7.5, 3.0, np.pi), (5.0, 1.0, 1.0), (3.0, 3.0, -1.0)])
    sensor = SensorConfig(resolution=(8, 32), kind="pallas", pallas_interpret=True, materials="instance")
    env = ConavEnv(episodes=split, config=EnvConfig(sensor=sensor))
    reset = jax.vmap(env.reset_to_episode)
    run = jit_with_bank(env, lambda k, e: constrain_batch(reset(k, e).obs["rgbd"], mesh), mesh)
    args = (jax.random.split(jax.random.PRNGKey(3), 8), jnp.arange(8) % 4)
    args = args if mesh is None else shard_batch(args, mesh)
    out = np.asarray(run(*args), np.float64)
    text = run.lower(*args).as_text()
    return {"lanes": out.reshape(8, -1).sum(axis=1).tolist(),
            "per_device_kernel": any(m in text for m in ("manual_computation", "SPMDFullToShardShape"))}


def _child(tmp: str) -> dict:
    import jax

    from conav_jax.parallel import make_mesh

    mesh = make_mesh(DEVICES)
    out = {"devices": jax.device_count(), "mesh": mesh.size}
    for name, fn in (("loop", lambda m: _loop_losses(Path(tmp), m)), ("evaluate", _evaluate_metrics),
                     ("policy", _policy_updates), ("recording", _recording),
                     ("steps", _env_steps), ("pallas_partitioned", _pallas_partitioned)):
        out[name] = {"single": fn(None), "sharded": fn(mesh)}
    return out


# -- the tests ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """One child process with 4 host devices: each check on 1 device and on all 4."""
    # Compile time dominates: the cheapest XLA:CPU settings (same results, slower to run).
    flags = (f"--xla_force_host_platform_device_count={DEVICES} --xla_backend_optimization_level=0 "
             "--xla_cpu_use_fusion_emitters=false")
    env = {**os.environ, "XLA_FLAGS": flags, "PYTHONPATH": os.pathsep.join([str(ROOT), str(ROOT / "tests")])}
    tmp = tmp_path_factory.mktemp("sharding")
    proc = subprocess.run([sys.executable, __file__, str(tmp)], env=env, cwd=ROOT, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-4000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_child_process_sees_four_devices(runs):
    assert runs["devices"] == DEVICES and runs["mesh"] == DEVICES


def test_sharded_training_loop_gives_the_single_device_losses(runs):
    single, sharded = runs["loop"]["single"], runs["loop"]["sharded"]
    assert len(single["losses"]) == 4
    np.testing.assert_allclose(sharded["losses"], single["losses"], rtol=1e-5)
    np.testing.assert_allclose(sharded["w"], single["w"], rtol=1e-5, atol=1e-7)
    assert single["param_devices"] == 1 and sharded["param_devices"] == DEVICES  # replicated


def test_sharded_evaluation_gives_identical_metrics(runs):
    single, sharded = runs["evaluate"]["single"], runs["evaluate"]["sharded"]
    assert single["episode"] == [0, 1, 2, 3, 4] and max(single["path_length_m"]) > 0.5  # it moved
    assert sharded == single


def test_env_steps_with_the_pallas_caster_run_on_every_device(runs):
    single, sharded = runs["steps"]["single"], runs["steps"]["sharded"]
    assert single["devices"] == 1 and sharded["devices"] == DEVICES
    assert len(set(single["lanes"])) > 1  # the lanes differ: a lane mix-up would show
    assert sharded["lanes"] == single["lanes"]


def test_pallas_caster_runs_per_device_inside_a_partitioned_program(runs):
    single, sharded = runs["pallas_partitioned"]["single"], runs["pallas_partitioned"]["sharded"]
    assert not single["per_device_kernel"] and sharded["per_device_kernel"]
    assert len(set(np.round(single["lanes"], 3))) > 1  # the lanes differ: a lane mix-up would show
    np.testing.assert_allclose(sharded["lanes"], single["lanes"], rtol=1e-6)


def test_sharded_policy_update_gives_the_single_device_loss(runs):
    single, sharded = runs["policy"]["single"], runs["policy"]["sharded"]
    assert single["bad"] == sharded["bad"] == -1
    np.testing.assert_allclose(sharded["losses"], single["losses"], rtol=1e-5)
    np.testing.assert_allclose(sharded["grad_norm_sum"], single["grad_norm_sum"], rtol=1e-5)
    assert single["losses"][0] > 0 and single["losses"][1] > 0
    np.testing.assert_allclose(sharded["params"], single["params"], rtol=1e-4, atol=1e-5)


def test_sharded_recording_keeps_the_single_device_windows(runs):
    single, sharded = runs["recording"]["single"], runs["recording"]["sharded"]
    assert single["windows"] > 5 and max(single["t_reach"]) >= 0  # the expert reached a goal: some episodes end early
    assert sharded == single
    assert sharded["advance_compiles"] == 1  # every chunk's carry placed alike: one program for all


def test_asking_for_more_devices_than_visible_is_refused():
    import jax

    from conav_jax.parallel import make_mesh

    n = jax.device_count()
    with pytest.raises(ValueError, match=rf"asked for {n + 1} devices but only {n} cpu device\(s\) are visible"):
        make_mesh(n + 1)
    with pytest.raises(ValueError, match="need at least 1 device, got 0"):
        make_mesh(0)
    assert make_mesh(None).size == n and make_mesh(None).axis_names == ("batch",)


def test_a_batch_that_does_not_split_evenly_names_its_size_and_the_device_count():
    from conav_jax import parallel

    mesh = SimpleNamespace(size=3)  # a 3-device mesh, as far as the check looks
    with pytest.raises(ValueError, match="batch size 8 is not divisible by the device count 3"):
        parallel.shard_batch({"x": np.zeros((8, 2))}, mesh)
    with pytest.raises(ValueError, match="leading batch axis"):
        parallel.shard_batch(np.float32(1.0), parallel.make_mesh(1))
    assert parallel.round_up(7, mesh) == 9 and parallel.round_up(7, None) == 7


def test_distributed_is_left_alone_for_a_single_process(monkeypatch):
    from conav_jax import parallel

    for var in ("JAX_COORDINATOR_ADDRESS", "SLURM_STEP_NUM_TASKS", "OMPI_COMM_WORLD_SIZE"):
        monkeypatch.delenv(var, raising=False)
    assert parallel.maybe_initialize_distributed() is False
    monkeypatch.setenv("SLURM_STEP_NUM_TASKS", "1")
    assert parallel.maybe_initialize_distributed() is False
    monkeypatch.setenv("JAX_COORDINATOR_ADDRESS", "localhost:1234")
    monkeypatch.setenv("JAX_NUM_PROCESSES", "two")
    with pytest.raises(ValueError, match="JAX_NUM_PROCESSES must be an integer, got 'two'"):
        parallel.maybe_initialize_distributed()


if __name__ == "__main__":
    print(json.dumps(_child(sys.argv[1])))
