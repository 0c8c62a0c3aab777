"""The `conav` command line (eval/cli.py): a bad --data fails before anything is created under --out."""

import json


def test_train_policy_with_missing_data_leaves_no_run_directory(tmp_path, capsys):
    from conav_jax.eval.cli import main

    missing, out = tmp_path / "no_such_dataset", tmp_path / "run"
    rc = main(["train", "policy", "--data", str(missing), "--out", str(out)])
    assert rc != 0
    assert not out.exists()
    assert "dataset directory not found" in capsys.readouterr().err


def test_train_policy_with_an_edited_manifest_leaves_no_run_directory(tmp_path, tiny_data):
    import shutil

    from conav_jax.eval.cli import main

    data, out = tmp_path / "data", tmp_path / "run"
    shutil.copytree(tiny_data, data)
    m = json.loads((data / "manifest.json").read_text())
    m["splits"]["train"]["shards"][0]["sha256"] = "0" * 64
    (data / "manifest.json").write_text(json.dumps(m))
    assert main(["train", "policy", "--data", str(data), "--out", str(out)]) != 0
    assert not out.exists()


def test_the_demos_commands_parse_and_its_predictor_crops_the_policys_panorama(tmp_path):
    """Every stage of `conav demo` is a valid command line, and the intention predictor is
    trained on the panoramas the policy and the evaluated agents render (else the policy stage
    refuses it)."""
    from conav_jax.eval.cli import build_parser
    from conav_jax.eval.demo import demo_commands

    commands = demo_commands(tmp_path, seed=0, resolution="16x64", train=True)
    parsed = {tuple(argv[:2]): build_parser().parse_args(argv) for argv in commands}
    assert tuple(parsed[("train", "intention")].resolution) == tuple(parsed[("train", "live")].resolution) == (16, 64)
    # By default the shipped agent is evaluated and nothing is trained; its own policy needs training.
    assert [argv[0] for argv in demo_commands(tmp_path, seed=0, resolution="16x64")] == ["generate", "eval", "view"]
    own = demo_commands(tmp_path, seed=0, resolution="16x64", pretrained=False)
    assert [argv[0] for argv in own] == ["generate", "train", "train", "train", "eval", "view"]
    assert build_parser().parse_args(["demo", "--out", "o", "--train"]).train


def test_each_demo_and_reproduce_stage_starts_from_cleared_jax_caches(tmp_path, monkeypatch):
    """As a fresh `conav` process would: a stage lowering functions traced by an earlier stage
    gets other compile-cache keys than a later run of the command, which then compiles again."""
    import jax

    from conav_jax.eval import cli
    from conav_jax.eval.demo import demo_commands

    events = []
    monkeypatch.setattr(jax, "clear_caches", lambda: events.append("clear"))
    monkeypatch.setattr(cli, "main", lambda argv, compile_cache=True: events.append(tuple(argv)) or 0)
    args = cli.build_parser().parse_args(["demo", "--out", str(tmp_path / "demo")])
    assert cli.demo.run(args) == 0
    stages = demo_commands(tmp_path / "demo", args.seed, "x".join(map(str, args.resolution)), args.pretrained, args.train)
    assert events == [x for argv in stages for x in ("clear", tuple(argv))]
    events.clear()
    from conav_jax.eval.cli import reproduce_steps

    monkeypatch.setattr(reproduce_steps, "step_function", lambda kind: lambda **kwargs: events.append(kind))
    args = cli.build_parser().parse_args(["reproduce", "--preset", "tiny", "--out", str(tmp_path / "r"), "--stage",
                                          "generate"])
    cli.reproduce.run(args)
    assert events[0] == "clear" and events[1] == "generate"


def test_output_read_only_in_part_stops_without_a_traceback(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    # `conav reproduce --dry-run` prints some thirty lines; `head -1` stops reading after one.
    cmd = (f"{sys.executable} -m conav_jax.eval.cli --compile-cache off reproduce --preset tiny --out {tmp_path / 'r'} --dry-run"
           " | head -1")
    proc = subprocess.run(["bash", "-o", "pipefail", "-c", cmd], cwd=root, capture_output=True, text=True, timeout=300,
                          check=False)
    assert proc.stdout.strip() == "[generate] to run (0 of 1 steps done; the 1 left have no time to go by)"
    assert "Traceback" not in proc.stderr and "BrokenPipeError" not in proc.stderr


def test_config_flags_carry_the_fields_type_default_and_documenting_comment():
    import argparse

    from conav_jax.eval.cli.args import add_fields, config_from_args, field_docs
    from conav_jax.train.loop import TrainConfig
    from conav_jax.train.ppo import PPOConfig

    assert field_docs(TrainConfig)["steps"] == "total updates (a resumed run continues up to this count)"
    assert field_docs(PPOConfig)["reset_every"].startswith("Iterations between re-resets")  # the block above it
    p = argparse.ArgumentParser()
    add_fields(p, TrainConfig, ("steps", "lr"), defaults=TrainConfig(steps=700), flags={"lr": "--learning-rate"})
    add_fields(p, PPOConfig, ("recurrent", "reset_every"))
    helps = {a.dest: a.help for a in p._actions}
    assert helps["steps"] == "total updates (a resumed run continues up to this count) (default 700)"
    args = p.parse_args(["--learning-rate", "0.5", "--no-recurrent", "--reset-every", "3"])
    assert config_from_args(TrainConfig, args) == TrainConfig(steps=700, lr=0.5)
    assert config_from_args(PPOConfig, args) == PPOConfig(recurrent=False, reset_every=3)


def test_library_errors_name_flags_where_the_command_maps_the_field():
    from conav_jax.eval.cli import build_parser
    from conav_jax.eval.cli.args import as_flags

    flags = build_parser().parse_args(["train", "rl", "--data", "d", "--out", "o"]).field_flags
    message = "TrainConfig.steps and PPOConfig.total_env_steps and gpu_slots.gpus and metrics.json"
    assert as_flags(message, flags) == "TrainConfig.steps and --steps and gpu_slots.gpus and metrics.json"
    flags = build_parser().parse_args(["train", "intention", "--data", "d", "--out", "o"]).field_flags
    assert as_flags("TrainConfig.steps, PerceiverConfig.num_latents", flags) == "--steps, --latents"


def test_bench_eval_untrained_refuses_a_run_and_accepts_agents_outside_the_registry(tmp_path, monkeypatch, capsys):
    from conav_jax.eval import cli

    base = ["--compile-cache", "off", "bench", "eval", "--data", str(tmp_path / "none")]
    assert cli.main([*base, "--agent", "conav", "--untrained", "--checkpoint", str(tmp_path)]) == 2
    assert "--untrained builds the agent from fresh weights" in capsys.readouterr().err
    assert cli.main([*base, "--agent", "random", "--profile-chunks", "0"]) == 2
    assert "--profile-chunks and --episodes must be at least 1" in capsys.readouterr().err
    # A name outside the registry reaches make_agent (package.module:factory agents), not a check before it.
    seen = []

    def make_agent(name, *args, **kwargs):
        seen.append(name)
        raise ValueError("built here")

    monkeypatch.setattr("conav_jax.envs.agents.registry.make_agent", make_agent)
    monkeypatch.setattr("conav_jax.envs.ConavEnv", lambda *a, **k: None)
    assert cli.main([*base, "--agent", "mypkg.agents:make", "--resolution", "8x32"]) == 2
    assert seen == ["mypkg.agents:make"] and "built here" in capsys.readouterr().err
    # An untrained agent's network: the paper runs' (patch, bfloat16) unless set; a trained run's is its own.
    assert cli.main([*base, "--agent", "conav", "--encoder", "conv"]) == 2
    assert "--encoder and --conv-dtype set an untrained agent's network" in capsys.readouterr().err
    built = {}

    def untrained_agent(name, env, config, key):
        built[name] = config
        raise ValueError("built here")

    from types import SimpleNamespace

    sensor = SimpleNamespace(resolution=(8, 32))
    monkeypatch.setattr("conav_jax.envs.ConavEnv", lambda *a, **k: SimpleNamespace(config=SimpleNamespace(sensor=sensor)))
    monkeypatch.setattr("conav_jax.eval.bench.untrained_agent", untrained_agent)
    from conav_jax.models.policy import encoder_name

    assert cli.main([*base, "--agent", "conav", "--untrained", "--resolution", "8x32"]) == 2
    assert (encoder_name(built["conav"]), built["conav"].conv_dtype) == ("patch", "bfloat16")
    assert cli.main([*base, "--agent", "imagegoal", "--untrained", "--resolution", "8x32", "--encoder", "patch",
                     "--conv-dtype", "float32"]) == 2
    goal = built["imagegoal"]
    assert (encoder_name(goal), goal.conv_dtype, goal.goal_image, goal.resolution) == ("patch", "float32", True, (8, 32))


def test_bench_sim_times_each_material_and_passes_the_shading_switch(monkeypatch, capsys):
    from conav_jax.eval import cli

    seen = []

    class Env:
        def __init__(self, data, split, config):
            self.config = config

    def bench_sim(env, batch, steps, repeats, what, mesh, materials):
        seen.append((materials, env.config.sensor.pallas_shade, env.config.sensor.kind))
        return {"materials": materials}

    monkeypatch.setattr("conav_jax.envs.ConavEnv", Env)
    monkeypatch.setattr("conav_jax.envs.bench.bench_sim", bench_sim)
    base = ["bench", "sim", "--data", "d", "--devices", "1", "--sensor", "pallas", "--json"]
    assert cli.main([*base, "--materials", "flat", "instance"]) == 0
    assert cli.main([*base, "--no-pallas-shade"]) == 0
    assert seen == [("flat", True, "pallas"), ("instance", True, "pallas"), ("instance", False, "pallas")]
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert [x["materials"] for x in lines] == ["flat", "instance", "instance"]
    assert [x["pallas"]["shade"] for x in lines] == [True, True, False]



def test_bench_sim_one_device_modes_name_the_argument_and_the_flag(monkeypatch, capsys):
    from types import SimpleNamespace

    import pytest

    from conav_jax.envs.bench import bench_sim
    from conav_jax.eval import cli

    two = SimpleNamespace(size=2)
    with pytest.raises(ValueError, match="^bench_sim.what compile runs on one device: bench_sim.mesh must hold one"):
        bench_sim(None, 4, 1, 1, "compile", two)
    monkeypatch.setattr("conav_jax.envs.ConavEnv", lambda data, split, config: SimpleNamespace(config=config))
    monkeypatch.setattr("conav_jax.parallel.make_mesh", lambda n: SimpleNamespace(size=n))
    assert cli.main(["bench", "sim", "--data", "d", "--what", "breakdown", "--devices", "2"]) == 2
    assert "error: --what breakdown runs on one device: --devices must hold one, not 2" in capsys.readouterr().err


def test_bench_train_policy_options_name_the_arguments_and_the_flags(capsys):
    import pytest

    from conav_jax.eval import cli
    from conav_jax.train.bench import bench_train

    with pytest.raises(ValueError, match="^bench_train.remat, bench_train.conv_dtype and bench_train.encoder apply"):
        bench_train("trajectory", 2, (8, 32), 1, 1, remat=True)
    assert cli.main(["bench", "train", "--model", "trajectory", "--remat", "--devices", "1"]) == 2
    err = capsys.readouterr().err
    assert "error: --remat, --conv-dtype and --encoder apply to the policy model, not --model trajectory" in err

def test_train_live_builds_its_configs_from_flags_and_passes_the_predictors(tmp_path, monkeypatch, capsys):
    from conav_jax.eval import cli
    from conav_jax.train.live import LiveConfig

    calls = []

    def train_live_from_data(data, out, model, live, **kwargs):
        calls.append((data, out, model, live, kwargs))
        raise FloatingPointError("stopped here")

    monkeypatch.setattr("conav_jax.train.live.train_live_from_data", train_live_from_data)
    base = ["train", "live", "--data", "d", "--out", str(tmp_path / "run"), "--resolution", "8x32"]
    assert cli.main([*base, "--ground-truth-intentions", "--lanes", "64", "--window-steps", "8", "--beta-end", "0.25",
                     "--ablation", "object", "--no-progress"]) == 1
    data, out, model, live, kwargs = calls[-1]
    assert live == LiveConfig(lanes=64, window_steps=8, beta_end=0.25)
    assert model.resolution == (8, 32) and (model.use_activity, model.use_object, model.use_trajectory) == (False, True, False)
    assert kwargs["intention_run"] is None and kwargs["trajectory_run"] is None
    assert model.uses_saliency  # the object input as a saliency map too, as `conav train policy` reads it
    assert cli.main([*base, "--ground-truth-intentions", "--ablation", "object", "--no-object-saliency"]) == 1
    assert not calls[-1][2].uses_saliency and calls[-1][2].use_object
    assert cli.main([*base, "--intention", "I", "--trajectory", "T"]) == 1
    assert calls[-1][4]["intention_run"] == "I" and calls[-1][4]["trajectory_run"] == "T"
    assert cli.main([*base, "--intention", "I"]) == 2  # all inputs read the trajectory predictor
    assert "--trajectory RUN" in capsys.readouterr().err


def test_train_live_asks_for_an_intention_source_only_where_the_ablation_reads_one(tmp_path, capsys):
    from conav_jax.eval.cli import main

    common = ["train", "live", "--data", str(tmp_path / "no_such_dataset"), "--out", str(tmp_path / "run")]
    assert main([*common, "--ablation", "object"]) == 2
    assert "--ablation object reads intentions: give --intention RUN" in capsys.readouterr().err
    assert main([*common, "--ablation", "none"]) == 2  # reads none: on to the data, which are missing
    assert "dataset directory not found" in capsys.readouterr().err


def test_bench_eval_times_a_policy_on_the_materials_and_panorama_it_was_trained_on(tmp_path, monkeypatch, capsys,
                                                                                 runs_32x128):
    import json
    from types import SimpleNamespace

    from conav_jax.eval import cli
    from conav_jax.envs.config import run_materials
    from conav_jax.pretrained import pretrained_runs

    built = {}

    def env(data, split, config, **kwargs):
        built["materials"] = config.sensor.materials
        built["resolution"] = config.sensor.resolution
        return SimpleNamespace(config=config)

    def make_agent(name, env, checkpoint, **kwargs):
        built.update(agent=name, checkpoint=checkpoint, intention=kwargs.get("intention_run"))
        return "agent"

    monkeypatch.setattr("conav_jax.envs.ConavEnv", env)
    monkeypatch.setattr("conav_jax.envs.agents.registry.make_agent", make_agent)
    monkeypatch.setattr("conav_jax.eval.bench.bench_sweep", lambda *a, **k: {"timed": True})
    base = ["--compile-cache", "off", "bench", "eval", "--data", str(tmp_path), "--agent", "conav", "--json"]
    # A run trained on flat colours at 32x128 (not the defaults) is timed on those.
    own = ["--checkpoint", str(runs_32x128["policy"]), "--intention", str(runs_32x128["intention"]),
           "--trajectory", str(runs_32x128["trajectory"])]
    assert cli.main([*base, *own]) == 0
    assert built == {"materials": "flat", "resolution": (32, 128), "agent": "conav",
                     "checkpoint": str(runs_32x128["policy"]), "intention": str(runs_32x128["intention"])}
    assert json.loads(capsys.readouterr().out)["materials"] == "flat"
    assert cli.main([*base, "--pretrained"]) == 0
    runs = pretrained_runs()
    assert built == {"materials": run_materials(runs["policy"]), "resolution": (112, 448), "agent": "conav",
                     "checkpoint": str(runs["policy"]), "intention": None}
    assert cli.main([*base, "--pretrained", "--checkpoint", str(tmp_path)]) == 2
    assert "--pretrained is the conav agent's run: drop its --checkpoint" in capsys.readouterr().err

