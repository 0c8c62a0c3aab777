"""`conav eval` and its report: intervals and tables on hand-built results, the sweep's files,
determinism, and input errors raised before anything is compiled."""

import csv
import dataclasses
import json
import re
import textwrap

import numpy as np
import pytest

from conav_jax.eval import sweep
from conav_jax.eval.report import (
    bootstrap_interval,
    summarize_with_ci,
    table2_markdown,
    table3_markdown,
    wilson_interval,
)


def _metrics(rows):
    """Env-style final metrics from (t_reach, t_arrive, t_end, collided_before_reach, collided,
    shortest path steps l, geodesic metres, path metres) per episode."""
    names = ("t_reach", "t_arrive", "t_end", "collided_before_reach", "collided", "shortest_path_steps",
             "geodesic_start_goal_m", "path_length_m")
    return {n: np.array([r[i] for r in rows], np.float32) for i, n in enumerate(names)}


# First before the human (SPL 8 / 10 steps = 0.8; 5 / 6.25 m = 0.8), after the human but in time
# (SPL 1), never with a touch.
THREE = _metrics([(10, 20, 40, 0, 0, 8, 5.0, 6.25), (30, 20, 40, 0, 0, 30, 4.0, 4.0), (-1, 20, 50, 0, 1, 20, 3.0, 9.0)])


def test_wilson_interval_matches_hand_computed_endpoints():
    # z = 1.96: 1/3 -> centre (1/3 + z^2/6) / (1 + z^2/3) = 0.42692, half 0.36543
    assert wilson_interval(1, 3) == pytest.approx((0.06149, 0.79234), abs=1e-4)
    assert wilson_interval(2, 3) == pytest.approx((0.20766, 0.93851), abs=1e-4)
    assert wilson_interval(0, 3) == pytest.approx((0.0, 0.56151), abs=1e-4)
    with pytest.raises(ValueError, match="at least one trial"):
        wilson_interval(0, 0)


def test_metrics_of_three_known_episodes():
    s = summarize_with_ci(THREE, seed=0)
    assert s["FASR"]["value"] == pytest.approx(100 / 3)
    assert s["RASR"]["value"] == pytest.approx(200 / 3)
    assert s["FASPL"]["value"] == pytest.approx(80 / 3, abs=1e-4)
    assert s["RASPL"]["value"] == pytest.approx(180 / 3, abs=1e-4)
    assert s["CR"]["value"] == pytest.approx(100 / 3)
    assert s["AS"]["value"] == pytest.approx(30.0)  # (10 + 30 + 50) / 3: t_end when never reached
    assert (s["FASR"]["lo"], s["FASR"]["hi"]) == pytest.approx((6.149, 79.234), abs=1e-2)
    assert (s["RASR"]["lo"], s["RASR"]["hi"]) == pytest.approx((20.766, 93.851), abs=1e-2)
    # Bootstrap: the 2.5 / 97.5 percentiles of 2000 seeded resamples of the episode values.
    rng = np.random.default_rng(0)
    means = np.array([0.8, 0.0, 0.0])[rng.integers(0, 3, size=(2000, 3))].mean(axis=1)
    assert (s["FASPL"]["lo"], s["FASPL"]["hi"]) == pytest.approx(tuple(100 * np.percentile(means, [2.5, 97.5])))
    assert summarize_with_ci(THREE, seed=0) == s


def test_bootstrap_is_seeded_and_degenerate_for_constants():
    v = np.array([0.0, 0.5, 1.0, 0.25])
    assert bootstrap_interval(v, seed=3) == bootstrap_interval(v, seed=3)
    assert bootstrap_interval(np.full(5, 2.0)) == (2.0, 2.0)


def test_tables_are_laid_out_like_the_paper():
    s = summarize_with_ci(THREE, seed=0)
    t2 = table2_markdown([("Pioneer Agent (Oracle Pathfinder)", s)]).splitlines()
    assert t2[0] == "| Methods | FASR↑ | RASR↑ | FASPL↑ | RASPL↑ | CR↓ | AS↓ | FASPL_m↑ | RASPL_m↑ |"
    half = (79.234 - 6.149) / 2
    assert t2[2].startswith(f"| Pioneer Agent (Oracle Pathfinder) | 33.3 ± {half:.1f} | 66.7 ± ")
    assert "| 30.0 ± " in t2[2]
    t3 = table3_markdown([("none", (False, False, False), s), ("all", (True, True, True), s), ("x", (None, True, None), s)]).splitlines()
    assert t3[0].startswith("| Exp. | Activity | Object | Trajectory | FASR↑")
    assert t3[2].startswith("| none | ✗ | ✗ | ✗ | 33.3")
    assert t3[3].startswith("| all | ✓ | ✓ | ✓ |") and t3[4].startswith("| x | ? | ✓ | ? |")


def _args(*argv):
    from conav_jax.eval.cli import build_parser

    return build_parser().parse_args(["eval", *argv])


def run_eval(args):
    """`conav eval` as the command line runs it, errors raised rather than printed."""
    return args.func(args)


@pytest.fixture(scope="module")
def two_sweeps(tiny_data, tmp_path_factory):
    """The same sweep twice (same seed) into two directories; 3 episodes on 4 lanes (one
    full-length batch: tests/test_rollout.py checks it against refilled lanes)."""
    outs = [tmp_path_factory.mktemp(f"sweep{k}") for k in range(2)]
    sweep._ENV_CACHE.clear()  # an env of its own, holding only these sweeps' evaluators, whatever ran before
    for out in outs:
        argv = ["--data", str(tiny_data), "--agent", "objectgoal-planner,random,pioneer", "--episodes", "3", "--batch", "4",
                "--resolution", "8x32", "--seed", "1", "--out", str(out)]
        assert run_eval(_args(*argv)) == 0
    return outs


def test_sweep_writes_records_metrics_report_and_figures(two_sweeps):
    out = two_sweeps[0]
    for name in ("episodes_objectgoal-planner.csv", "metrics.json", "report.md", "success_over_time.png", "map_objectgoal-planner.png"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    rows = list(csv.DictReader((out / "episodes_objectgoal-planner.csv").open()))
    assert [r["episode"] for r in rows] == ["0", "1", "2"]
    # Every row says what the agent was given.
    assert {(r["agent"], r["intention_source"], r["privileged"]) for r in rows} == {
        ("objectgoal-planner", "none", "oracle goal category;oracle map")}
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["episodes"] == 3 and doc["ablations"] == {}
    entry = doc["agents"]["objectgoal-planner"]
    assert entry["title"] == "Object-goal planner (oracle goal category + oracle map)"
    assert entry["intention_source"] == "none" and entry["privileged"] == ["oracle goal category", "oracle map"]
    # The metrics are the per-episode records' means, CR_full included (episodes run to t_end).
    m = entry["metrics"]
    for name, column in (("FASR", "FASR"), ("FASPL", "FASPL"), ("CR", "collided"), ("CR_full", "collided_full")):
        assert m[name]["value"] == pytest.approx(100 * np.mean([float(r[column]) for r in rows]), abs=1e-3), name
    # ...and the observation keys each reads.
    # (Scripted agents read the simulator's state, which the row says beside the keys.)
    assert entry["reads"] == [] and doc["agents"]["pioneer"]["reads"] == ["human_history"]
    assert entry["reads_state"] and doc["agents"]["pioneer"]["reads_state"]
    report = (out / "report.md").read_text()
    assert "| Object-goal planner (oracle goal category + oracle map) | none | oracle goal category, oracle map | " \
           "the simulator's state |" in report
    assert "| Pioneer Agent (candidate goal points + pose set by an oracle pathfinder) | none | candidate goal points, " \
           "pose set by an oracle pathfinder | `human_history`, the simulator's state |" in report
    assert "| CR↓ | CR_full↓ |" in report and "![success by step](success_over_time.png)" in report
    assert (out / "map_objectgoal-planner.png").read_bytes()[:4] == b"\x89PNG"


def test_scripted_agents_share_one_compiled_rollout_with_their_own_results(two_sweeps):
    from conav_jax.envs.agents.registry import make_agent
    from conav_jax.envs.rollout import evaluate

    out = two_sweeps[0]
    env = next(iter(sweep._ENV_CACHE.values()))
    # One evaluator serves the scripted agents (the agent is data), the pioneer's poses with the
    # others' velocities, for both sweeps...
    assert len(sweep._EVALUATORS[env]) == 1
    # ...and gives each the results it gets alone.
    for name in ("objectgoal-planner", "pioneer"):
        alone = evaluate(env, make_agent(name, env), batch=4, seed=1)
        rows = list(csv.DictReader((out / f"episodes_{name}.csv").open()))
        assert [int(r["t_reach"]) for r in rows] == alone["t_reach"].astype(int).tolist(), name
        for key in ("path_length_m", "collided_full"):  # the CSV's 4 decimals
            np.testing.assert_allclose([float(r[key]) for r in rows], alone[key], rtol=0, atol=1e-4, err_msg=name)
    rows = list(csv.DictReader((out / "episodes_objectgoal-planner.csv").open()))
    # The random agent's rows are its own, not the planner's again.
    random_rows = list(csv.DictReader((out / "episodes_random.csv").open()))
    assert [r["t_reach"] for r in random_rows] != [r["t_reach"] for r in rows]


def test_same_seed_gives_identical_metrics_bytes(two_sweeps):
    a, b = two_sweeps
    assert (a / "metrics.json").read_bytes() == (b / "metrics.json").read_bytes()
    assert (a / "episodes_objectgoal-planner.csv").read_bytes() == (b / "episodes_objectgoal-planner.csv").read_bytes()


def test_every_agent_is_built_before_the_first_rollout(two_sweeps, tiny_data, tmp_path):
    # An existing but empty run dir passes the cheap checks; loading it fails, and it must fail
    # before the agent listed first (objectgoal-planner) is evaluated.
    (tmp_path / "empty_run").mkdir()
    out = tmp_path / "o"
    argv = ["--data", str(tiny_data), "--agent", "objectgoal-planner,conav", "--checkpoint", str(tmp_path / "empty_run")]
    with pytest.raises((ValueError, FileNotFoundError)):
        run_eval(_args(*argv, "--episodes", "3", "--batch", "2", "--resolution", "8x32", "--out", str(out)))
    assert not (out / "episodes_objectgoal-planner.csv").exists()


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--agent", "pioneer,nope"], "unknown agent 'nope'"),
        (["--agent", "conav"], "needs a trained run"),
        (["--agent", "conav", "--checkpoint", "/nonexistent/run"], "run directory not found"),
        (["--agent", "pioneer", "--ablation-checkpoints", "all"], "name=RUN_DIR"),
        (["--agent", "pioneer", "--ablation-checkpoints", "all=/nonexistent/run"], "run directory not found"),
        (["--agent", "pioneer", "--split", "test"], "no split 'test'"),
        (["--agent", "pioneer", "--batch", "0"], "EvalPlan.batch must be at least 1"),
    ],
)
def test_bad_input_fails_before_anything_is_built(tiny_data, tmp_path, monkeypatch, argv, message):
    def never(*a, **k):
        raise AssertionError("the env was built before the inputs were checked")

    monkeypatch.setattr(sweep, "load_env", never)
    with pytest.raises(ValueError, match=message):
        run_eval(_args("--data", str(tiny_data), "--out", str(tmp_path / "o"), *argv))


def test_a_user_agents_files_are_named_safely_and_record_what_it_reads(tiny_data, tmp_path, monkeypatch):
    (tmp_path / "sweep_agents.py").write_text(textwrap.dedent("""
        import jax.numpy as jnp
        import conav_jax

        def still():
            return conav_jax.Agent("Standing still", lambda key, obs: (), lambda carry, obs, key: (carry, jnp.zeros(2)),
                                   reads=("gps_compass", "human_pos"))
    """))
    monkeypatch.syspath_prepend(str(tmp_path))
    out = tmp_path / "o"
    assert run_eval(_args("--data", str(tiny_data), "--agent", "sweep_agents:still", "--episodes", "2", "--batch", "2",
                          "--resolution", "8x32", "--out", str(out))) == 0
    names = sorted(p.name for p in out.iterdir())
    assert all(re.fullmatch(r"[A-Za-z0-9_.-]+", n) for n in names), names
    assert {"episodes_sweep_agents.still.csv", "map_sweep_agents.still.png"} <= set(names)
    entry = json.loads((out / "metrics.json").read_text())["agents"]["sweep_agents:still"]
    assert entry["title"] == "Standing still" and entry["reads"] == ["gps_compass", "human_pos"] and not entry["reads_state"]
    report = (out / "report.md").read_text()
    assert "| Standing still | none | none | `gps_compass`, `human_pos` |" in report
    assert "(map_sweep_agents.still.png)" in report


def test_agents_whose_files_would_share_a_name_are_refused(tiny_data, tmp_path, monkeypatch):
    assert sweep.file_stem("pkg.mod:make") == "pkg.mod.make" and sweep.file_stem("a b/c") == "a_b_c"
    (tmp_path / "twin").mkdir()
    (tmp_path / "twin" / "__init__.py").write_text("from . import mod\n")
    (tmp_path / "twin" / "mod.py").write_text("def make():\n    return None\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    # Different factories' names, one file name: twin.mod.make.
    with pytest.raises(ValueError, match="'twin.mod:make' and 'twin:mod.make' would both write episodes_twin.mod.make.csv"):
        sweep.plan_eval(tiny_data, "val", ("twin.mod:make", "twin:mod.make"), tmp_path / "o")
    sweep.plan_eval(tiny_data, "val", ("twin.mod:make", "random"), tmp_path / "o")  # distinct names pass


def test_missing_dataset_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="dataset directory not found"):
        run_eval(_args("--data", str(tmp_path / "none"), "--agent", "random", "--out", str(tmp_path / "o")))


def test_learning_curve_pools_reach_rates_over_reset_cycles(tmp_path):
    from conav_jax.eval.plots import learning_curve, pooled_reach_rate

    # Iterations of 100 env steps: 2 of 4 episodes reached, then 0 of 1, 3 of 3, 1 of 2, and a
    # cut-off cycle's quick successes (dropped).
    train = [
        {"split": "train", "env_steps": 100, "episodes": 4, "reach_rate": 0.5},
        {"split": "train", "env_steps": 200, "episodes": 1, "reach_rate": 0.0},
        {"split": "train", "env_steps": 300, "episodes": 3, "reach_rate": 1.0},
        {"split": "train", "env_steps": 400, "episodes": 2, "reach_rate": 0.5},
        {"split": "train", "env_steps": 500, "episodes": 5, "reach_rate": 1.0, "reset_every": 2},
    ]
    x, rate = pooled_reach_rate(train, window=2)
    np.testing.assert_allclose(x, [200, 400])
    np.testing.assert_allclose(rate, [2 / 5, 4 / 5])
    np.testing.assert_allclose(pooled_reach_rate(train[:1], window=2)[1], [0.5])  # only a partial one: kept
    val = {"split": "val", "env_steps": 300, "FASR": 10.0, "RASR": 20.0}
    out = learning_curve({"run": train + [val]}, tmp_path / "curve.png")  # window: the run's reset_every
    assert out.stat().st_size > 1000
    with pytest.raises(ValueError, match="no PPO training records"):
        learning_curve({"imitation": [{"split": "train", "step": 10, "loss": 0.1}]}, tmp_path / "bad.png")


@pytest.fixture(scope="module")
def policy_runs(tiny_data, tmp_path_factory, runs_32x128):
    """A trained CoNav policy and a copy with other weights (every float scaled by 0.8): two runs
    of one configuration, with the predictors they read, on 2 val episodes at their 32x128 (the
    env `conav eval --checkpoint RUN --episodes 2` loads, kept by eval.sweep.load_env)."""
    from types import SimpleNamespace

    import jax

    from conav_jax import runs
    from conav_jax.checkpoints import checkpoint_path, save_checkpoint

    shipped = runs_32x128
    ckpt = runs.load_run(shipped["policy"], runs.POLICY)
    other = tmp_path_factory.mktemp("other_policy")
    scaled = jax.tree.map(lambda v: v * np.float32(0.8) if np.issubdtype(v.dtype, np.floating) else v, ckpt.params)
    save_checkpoint(checkpoint_path(other, ckpt.step), params=scaled, opt_state=None, config=ckpt.config,
                    step=ckpt.step, extra=ckpt.extra)
    kw = {"intention_run": str(shipped["intention"]), "trajectory_run": str(shipped["trajectory"])}
    plan = sweep.plan_eval(tiny_data, "val", ("conav",), tmp_path_factory.mktemp("o"),
                           checkpoint=str(shipped["policy"]), intention_kwargs=kw, episodes=2, batch=2)
    return SimpleNamespace(env=sweep.load_env(plan), runs=(str(shipped["policy"]), str(other)), kw=kw)


def test_runs_of_one_configuration_share_one_compiled_rollout(policy_runs, monkeypatch):
    """Two runs of one configuration evaluate through one compiled rollout, their weights its
    arguments, each with its own numbers: the second's are, bit for bit, those of a rollout
    compiled around its weights as constants."""
    from conav_jax.envs import rollout
    from conav_jax.envs.agents.registry import make_agent
    from conav_jax.parallel import make_mesh

    traced, real = [], rollout.as_state_agent
    # A rollout builds its agent once per trace.
    monkeypatch.setattr(rollout, "as_state_agent", lambda agent: traced.append(agent.name) or real(agent))
    env, kw = policy_runs.env, policy_runs.kw
    sweep._EVALUATORS.pop(env, None)  # compiled here, whatever ran before (later sweeps of the run reuse it)
    episodes = np.arange(env.num_episodes)
    # On the mesh `conav eval` splits lanes over (one device here), which replicates the weights.
    built = sweep.build_evaluators(env, [("conav", run, kw) for run in policy_runs.runs], 2, 0, make_mesh(None))
    (_, _, path_a), (metrics, first, path) = (evaluate(episodes) for _, evaluate in built)
    assert traced == ["conav"]
    assert not np.array_equal(path_a, path)  # each run acts with its own weights
    agent = make_agent("conav", env, policy_runs.runs[1], **kw)
    closed, closed_first, trace = rollout.make_evaluator(env, lambda _: agent, 2, 0, trace_first=True)(None, episodes)
    assert first == closed_first and set(metrics) == set(closed)
    np.testing.assert_array_equal(path, trace.robot_pose)
    for k, v in closed.items():
        np.testing.assert_array_equal(metrics[k], v, err_msg=k)


def test_a_runs_weights_are_arguments_of_its_rollout_not_constants(policy_runs):
    """The rollouts of two runs of one configuration lower to one program, so the persistent
    compile cache finds the first's for the second; no array of their checkpoints (the policies'
    and the predictors') is a constant of it."""
    import jax
    import jax.numpy as jnp

    from conav_jax import runs
    from conav_jax.envs.agents.lift import lift_agent
    from conav_jax.envs.agents.registry import make_agent
    from conav_jax.envs.rollout import make_param_rollout

    env, kw = policy_runs.env, policy_runs.kw
    texts = []
    for run in policy_runs.runs:
        lifted = lift_agent(env, make_agent("conav", env, run, **kw))
        lowered = make_param_rollout(env, lifted.agent_fn, 4).lower(lifted.params, jax.random.PRNGKey(0),
                                                                    jnp.arange(2, dtype=jnp.int32))
        texts.append(lowered.as_text())
    assert texts[0] == texts[1]
    checkpoints = [(run, runs.POLICY) for run in policy_runs.runs]
    checkpoints += [(kw["intention_run"], runs.INTENTION), (kw["trajectory_run"], runs.TRAJECTORY)]
    weights = [np.asarray(w) for run, kind in checkpoints for w in jax.tree.leaves(runs.load_run(run, kind).params)]
    assert len(weights) > 50
    assert [w.shape for w in weights if w.size >= 16 and w.tobytes().hex().upper() in texts[1]] == []


def test_a_run_listed_as_agent_and_ablation_is_swept_once_with_the_same_numbers(tiny_data, tmp_path, monkeypatch,
                                                                              runs_32x128):
    calls = []
    real = sweep._evaluate_with

    def counting(evaluator, params):
        run = real(evaluator, params)
        return lambda episodes: calls.append(len(episodes)) or run(episodes)

    monkeypatch.setattr(sweep, "_evaluate_with", counting)
    policy_run = runs_32x128["policy"]
    out = tmp_path / "o"
    argv = ["--data", str(tiny_data), "--agent", "conav", "--checkpoint", str(policy_run),
            "--intention", str(runs_32x128["intention"]), "--trajectory", str(runs_32x128["trajectory"]),
            "--ablation-checkpoints", f"all={policy_run}",
            "--episodes", "2", "--batch", "2", "--resolution", "32x128", "--out", str(out)]
    assert run_eval(_args(*argv)) == 0
    assert calls == [2]
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["ablations"]["ablation_all"]["metrics"] == doc["agents"]["conav"]["metrics"]
    assert doc["ablations"]["ablation_all"]["title"].startswith("all: ")
    assert doc["agents"]["conav"]["trained"] == sweep.trained_with(policy_run)  # the weights' own record
    assert doc["agents"]["conav"]["trained"]["run"] == str(policy_run)
    agent_rows, ablation_rows = (list(csv.DictReader((out / f"episodes_{k}.csv").open())) for k in ("conav", "ablation_all"))
    assert [r["t_reach"] for r in agent_rows] == [r["t_reach"] for r in ablation_rows]


def test_the_command_line_names_the_flags_of_the_fields_a_library_error_names(tiny_data, tmp_path, capsys):
    from conav_jax.eval.cli import main

    base = ["--compile-cache", "off", "eval", "--data", str(tiny_data), "--out", str(tmp_path / "o")]
    assert main([*base, "--agent", "pioneer", "--batch", "0"]) == 2
    assert "error: --batch must be at least 1, got 0" in capsys.readouterr().err
    assert main([*base, "--agent", "pioneer,pioneer"]) == 2
    assert "error: --agent lists an agent twice" in capsys.readouterr().err


def test_untrained_learned_agents_act_from_fresh_weights_and_say_so(tiny_data, monkeypatch):
    """`conav bench eval --untrained`'s agents: built from `init` at the env's panorama, with
    fresh predictors where they read predictions; each acts and its title says untrained."""
    import jax
    import numpy as np

    from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
    import jax.numpy as jnp

    from conav_jax.envs.agents.base import as_state_agent
    from conav_jax.envs.rollout import _start, agent_step
    from conav_jax.eval.bench import UNTRAINED_AGENTS, untrained_agent
    from conav_jax.models import perceiver, policy, trajectory
    from conav_jax.models.policy import PolicyConfig, ablation_config

    made = []
    for model in (policy, perceiver, trajectory):  # zeros of init's shapes: the random draws compile slowly on CPU
        def zeros(key, config, init=model.init):
            made.append(type(config).__name__)
            shapes = jax.eval_shape(lambda k: init(k, config), key)
            return jax.tree.map(lambda x: jax.numpy.zeros(x.shape, x.dtype), shapes)

        monkeypatch.setattr(model, "init", zeros)

    env = ConavEnv(tiny_data, "val", EnvConfig(sensor=SensorConfig(resolution=(16, 64))))
    small = PolicyConfig(resolution=(16, 64), conv_channels=(4,), conv_kernels=(3,), visual_dim=8, state_dim=8,
                         intention_dim=8, hidden=8)
    configs = {"conav": small, "ppo": small, "imagegoal": dataclasses.replace(
        ablation_config(small, "none"), goal_image=True, use_human_pos=False)}
    goal = dataclasses.replace(ablation_config(small, "object"), use_human_pos=False)
    key = jax.random.PRNGKey(0)
    for name in UNTRAINED_AGENTS:
        agent = untrained_agent(name, env, configs.get(name, goal), key, frames=2)
        assert agent.name == name and agent.title.endswith("(untrained)")
        acting = as_state_agent(agent)  # shapes only: the agents are traced, not compiled
        state, carry, k = jax.eval_shape(lambda ep: _start(env, acting, key, ep), jnp.int32(0))
        _, action, _ = jax.eval_shape(lambda s, c, k: agent_step(env, acting, s, c, k), state, carry, k)
        assert action.shape == (2,) and action.dtype == np.float32
    assert set(made) == {"PolicyConfig", "PerceiverConfig", "TrajectoryConfig"}  # the weights are init's
    assert untrained_agent("conav", env, small, key, 2).intention_source == "predicted"
    with pytest.raises(ValueError, match="no untrained variant of agent 'pioneer'"):
        untrained_agent("pioneer", env, small, key, 2)
    with pytest.raises(ValueError, match="16x64"):
        untrained_agent("conav", env, dataclasses.replace(small, resolution=(8, 32)), key, 2)


def test_an_evaluation_names_the_run_step_and_code_its_weights_were_trained_with(tmp_path):
    from conav_jax.checkpoints import checkpoint_path, save_checkpoint

    run = tmp_path / "run"
    for step, commit in ((5, "older"), (9, "abc123")):
        save_checkpoint(checkpoint_path(run, step), params={"w": np.ones(2)}, opt_state=None, step=step,
                        config={"kind": "policy", "provenance": {"commit": commit, "dirty": False, "encoder": "patch"}})
    assert sweep.trained_with(run) == {"run": str(run), "step": 9,
                                       "provenance": {"commit": "abc123", "dirty": False, "encoder": "patch"}}
    assert sweep.trained_with(tmp_path / "elsewhere") == {"run": str(tmp_path / "elsewhere")}


def test_a_sweep_profile_names_what_it_needs_before_compiling(tiny_data):
    """A profiled sweep traces the refilling rollout on one device: each unmet need is named,
    before any compile."""
    from types import SimpleNamespace

    from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
    from conav_jax.envs.agents.base import Agent
    from conav_jax.eval.bench import bench_sweep

    env = ConavEnv(tiny_data, "val", EnvConfig(sensor=SensorConfig(resolution=(16, 64))))
    never = Agent("never acts", lambda key, obs: (), lambda carry, obs, key: 1 / 0)  # fails if it ever runs
    with pytest.raises(ValueError, match=r"needs more episodes \(3\) than lanes \(3\)"):
        bench_sweep(env, never, batch=3, repeats=1, episodes=3, profile_dir="trace")
    with pytest.raises(ValueError, match="runs on one device \\(mesh None\\), not a mesh of 2"):
        bench_sweep(env, never, batch=2, repeats=1, episodes=3, mesh=SimpleNamespace(size=2), profile_dir="trace")
    with pytest.raises(ValueError, match="profile_chunks must be at least 1, not 0"):
        bench_sweep(env, never, batch=2, repeats=1, episodes=3, profile_dir="trace", profile_chunks=0)
