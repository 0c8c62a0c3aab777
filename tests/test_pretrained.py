"""The policy and the predictors it reads, shipped with the package (conav_jax.pretrained), and the
`--pretrained` flag of `conav eval` / `conav view` / `conav demo`."""

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

from conav_jax import pretrained
from conav_jax.checkpoints import checkpoint_path, latest_checkpoint, load_checkpoint, save_checkpoint
from conav_jax.eval.cli import _use_pretrained, build_parser


def test_the_shipped_runs_load_fit_the_size_limit_and_say_where_they_come_from():
    from conav_jax.envs.agents.policy import needed_predictors, policy_config_from_dict

    runs = pretrained.pretrained_runs()
    files = [latest_checkpoint(d) for d in runs.values()]
    assert sum(f.stat().st_size for f in files) <= pretrained.SIZE_LIMIT_BYTES
    policy = load_checkpoint(files[0])
    assert policy.opt_state is None and policy.config["kind"] == "policy"
    # It names no predictor run of the machine it was trained on: eval passes the shipped one.
    assert policy.config["intention_run"] is None and policy.config["trajectory_run"] is None
    # Every predictor the policy reads is shipped beside it (the shipped policy reads none).
    model = policy_config_from_dict(policy.config["model"])
    assert set(runs) == {"policy", *needed_predictors(model)}
    prov = json.loads((pretrained.PRETRAINED_DIR / pretrained.PROVENANCE_FILE).read_text())
    assert prov["preset"] == "paper" and "FASR" in prov["val_4962_episodes"]
    assert prov["resolution"] == "x".join(map(str, model.resolution))
    assert prov["materials"] == policy.config["materials"]
    with pytest.raises(FileNotFoundError, match="missing from this install"):
        pretrained.pretrained_runs(Path("/nonexistent"))


def test_the_shipped_policy_reads_nothing_privileged():
    # What the package ships is the policy with no privileged input: panorama RGB-D, GPS +
    # compass and the human's position, no predictor, no segmentation.
    import jax

    from conav_jax.envs.agents.policy import needed_predictors, policy_config_from_dict

    policy = load_checkpoint(latest_checkpoint(pretrained.pretrained_runs()["policy"]))
    model = policy_config_from_dict(policy.config["model"])
    assert needed_predictors(model) == () and not model.uses_saliency
    # To fit the package: the flatten layer (most of the parameters) at int8, the rest at float16.
    stored = {str(leaf.dtype) for leaf in jax.tree.leaves(policy.params)}
    assert policy.params["visual"]["w"].dtype == np.float32 and stored == {"float32", "float16"}
    with zipfile.ZipFile(latest_checkpoint(pretrained.pretrained_runs()["policy"])) as zf:
        assert np.lib.format.read_array(zf.open("params/visual/w.npy")).dtype == np.int8


def test_the_shipped_conav_agent_builds_for_its_panorama_and_refuses_another(tiny_data):
    from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
    from conav_jax.envs.agents.registry import make_agent
    from conav_jax.envs.config import run_materials

    runs = pretrained.pretrained_runs()
    assert run_materials(runs["policy"]) == "instance"
    env = ConavEnv(tiny_data, "val", EnvConfig(sensor=SensorConfig(resolution=(112, 448), materials="instance")))
    agent = make_agent("conav", env, runs["policy"])
    assert agent.intention_source == "none" and "segmentation" not in agent.reads
    flat = ConavEnv(tiny_data, "val", EnvConfig(sensor=SensorConfig(resolution=(112, 448), materials="flat")))
    with pytest.raises(ValueError, match="materials='instance'.*materials='flat'"):
        make_agent("conav", flat, runs["policy"])
    small = ConavEnv(tiny_data, "val", EnvConfig(sensor=SensorConfig(resolution=(32, 128), materials="instance")))
    with pytest.raises(ValueError, match="112x448|\\(112, 448\\)"):
        make_agent("conav", small, runs["policy"])


def test_a_policy_with_predictors_builds_with_all_of_them_and_never_mixes_in_ground_truth(tiny_data, runs_32x128):
    from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
    from conav_jax.envs.agents.registry import make_agent

    runs = runs_32x128  # reads activity, object and trajectory inputs
    env = ConavEnv(tiny_data, "val", EnvConfig(sensor=SensorConfig(resolution=(32, 128), materials="flat")))
    agent = make_agent("conav", env, runs["policy"], intention_run=runs["intention"], trajectory_run=runs["trajectory"])
    assert agent.intention_source == "predicted"
    with pytest.raises(ValueError, match="reads trajectory predictions and no trajectory predictor run is given"):
        make_agent("conav", env, runs["policy"], intention_run=runs["intention"])
    with pytest.raises(ValueError, match="no intention predictor run is given"):
        make_agent("conav", env, runs["policy"], trajectory_run=runs["trajectory"])


def _eval_args(*extra):
    return build_parser().parse_args(["eval", "--data", "d", "--out", "o", *extra])


def test_pretrained_flag_names_the_shipped_runs_and_refuses_to_mix_with_others():
    runs = pretrained.pretrained_runs()
    args = _eval_args("--agent", "random,conav", "--pretrained")
    _use_pretrained(args, ("random", "conav"))
    assert args.checkpoint == str(runs["policy"])
    assert (args.intention, args.trajectory) == (None, None)  # the shipped policy reads no predictor
    # A bare RUN stays the other learned agents'.
    args = _eval_args("--agent", "conav,imagegoal", "--pretrained", "--checkpoint", "runs/imagenav")
    _use_pretrained(args, ("conav", "imagegoal"))
    assert args.checkpoint == f"runs/imagenav,conav={runs['policy']}"
    for agents, extra, match in ((("random",), (), "add conav"),
                                 (("conav",), ("--checkpoint", "runs/policy"), "drop its --checkpoint"),
                                 (("conav",), ("--checkpoint", "conav=runs/policy"), "drop its --checkpoint"),
                                 (("conav",), ("--intention", "runs/intention"), "its own predictors"),
                                 (("conav",), ("--trajectory", "runs/trajectory"), "its own predictors"),
                                 (("conav",), ("--ground-truth-intentions",), "its own predictors")):
        args = _eval_args("--agent", ",".join(agents), "--pretrained", *extra)
        with pytest.raises(ValueError, match=match):
            _use_pretrained(args, agents)
    args = _eval_args("--agent", "conav")  # without the flag nothing changes
    _use_pretrained(args, ("conav",))
    assert args.checkpoint is None and args.intention is None and args.trajectory is None


def test_the_demo_evaluates_and_records_the_shipped_policy_unless_told_not_to(tmp_path):
    from conav_jax.eval.demo import demo_commands

    for pretrained_on in (True, False):
        commands = {argv[0]: argv for argv in demo_commands(tmp_path, 0, "16x64", pretrained_on)}
        for stage in ("eval", "view"):
            assert ("--pretrained" in commands[stage]) == pretrained_on
            assert ("--checkpoint" in commands[stage]) != pretrained_on
    assert build_parser().parse_args(["demo", "--out", "x", "--no-pretrained"]).pretrained is False


def test_export_writes_parameters_only_and_checks_the_pair_and_the_size(tmp_path):
    params = {"w": np.ones((4, 4), np.float32)}
    save_checkpoint(checkpoint_path(tmp_path / "runs" / "intention", 6), params=params, opt_state={"m": params},
                    config={"kind": "intention"}, step=6)
    save_checkpoint(checkpoint_path(tmp_path / "runs" / "policy", 2), params=params, opt_state=None, step=2,
                    config={"kind": "policy", "intention_run": "/elsewhere/runs/intention", "trajectory_run": None})
    out = tmp_path / "shipped"
    size = pretrained.export_runs(tmp_path / "runs" / "policy", tmp_path / "runs" / "intention", {"what": "test"}, out)
    assert size == sum(latest_checkpoint(d).stat().st_size for d in pretrained.pretrained_runs(out).values())
    assert load_checkpoint(latest_checkpoint(out / "intention")).opt_state is None
    assert load_checkpoint(latest_checkpoint(out / "policy")).config["intention_run"] is None
    assert pretrained.pretrained_runs(out)["policy"] == out / "policy"
    save_checkpoint(checkpoint_path(tmp_path / "runs" / "other", 6), params=params, opt_state=None,
                    config={"kind": "intention"}, step=6)
    with pytest.raises(FileNotFoundError):  # a missing run is named, not a crash on None
        pretrained.export_runs(tmp_path / "runs" / "nothing", tmp_path / "runs" / "intention", {}, out)
    with pytest.raises(ValueError, match="read the intention run"):
        pretrained.export_runs(tmp_path / "runs" / "policy", tmp_path / "runs" / "other", {}, out)
    big = {"w": np.ones((pretrained.SIZE_LIMIT_BYTES // 4 + 1000,), np.float32)}
    save_checkpoint(checkpoint_path(tmp_path / "runs" / "policy", 3), params=big, opt_state=None, step=3,
                    config={"kind": "policy", "intention_run": "runs/intention", "trajectory_run": None})
    with pytest.raises(ValueError, match="over the package"):
        pretrained.export_runs(tmp_path / "runs" / "policy", tmp_path / "runs" / "intention", {}, out)
    assert load_checkpoint(latest_checkpoint(out / "policy")).step == 2  # the shipped runs stay as they were
    assert sorted(p.name for p in out.iterdir()) == ["PROVENANCE.json", "intention", "policy"]
    # A policy that read a trajectory predictor ships it too, and only with it.
    save_checkpoint(checkpoint_path(tmp_path / "runs" / "trajectory", 3), params=params, opt_state={"m": params},
                    config={"kind": "trajectory"}, step=3)
    save_checkpoint(checkpoint_path(tmp_path / "runs" / "policy", 4), params=params, opt_state=None, step=4,
                    config={"kind": "policy", "intention_run": "runs/intention", "trajectory_run": "/x/runs/trajectory"})
    with pytest.raises(ValueError, match="read the trajectory run"):
        pretrained.export_runs(tmp_path / "runs" / "policy", tmp_path / "runs" / "intention", {}, out)
    pretrained.export_runs(tmp_path / "runs" / "policy", tmp_path / "runs" / "intention", {}, out,
                           trajectory_run=tmp_path / "runs" / "trajectory")
    assert set(pretrained.pretrained_runs(out)) == {"policy", "intention", "trajectory"}
    assert load_checkpoint(latest_checkpoint(out / "trajectory")).opt_state is None
    assert load_checkpoint(latest_checkpoint(out / "policy")).config["trajectory_run"] is None
    # ... and a policy that read none drops the one shipped before.
    save_checkpoint(checkpoint_path(tmp_path / "runs" / "policy", 5), params=params, opt_state=None, step=5,
                    config={"kind": "policy", "intention_run": "runs/intention", "trajectory_run": None})
    with pytest.raises(ValueError, match="read the trajectory run None"):
        pretrained.export_runs(tmp_path / "runs" / "policy", tmp_path / "runs" / "intention", {}, out,
                               trajectory_run=tmp_path / "runs" / "trajectory")
    pretrained.export_runs(tmp_path / "runs" / "policy", tmp_path / "runs" / "intention", {}, out)
    assert set(pretrained.pretrained_runs(out)) == {"policy", "intention"}


def test_a_policy_that_reads_no_predictor_ships_alone_at_half_precision_and_acts(tmp_path, tiny_data):
    import dataclasses

    import jax

    from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
    from conav_jax.envs.agents.registry import make_agent
    from conav_jax.models import policy

    model = policy.ablation_config(policy.PolicyConfig(resolution=(16, 64)), "none")
    params = jax.device_get(policy.init(jax.random.PRNGKey(3), model))
    config = {"kind": "policy", "model": dataclasses.asdict(model), "materials": "instance", "intention_run": None,
              "trajectory_run": None}
    save_checkpoint(checkpoint_path(tmp_path / "runs" / "none", 7), params=params, opt_state={"m": params},
                    config=config, step=7)
    with pytest.raises(ValueError, match="weights_dtype 'bfloat8'"):
        pretrained.export_runs(tmp_path / "runs" / "none", None, {}, tmp_path / "x", weights_dtype="bfloat8")
    with pytest.raises(ValueError, match="read the intention run None"):  # it read no predictor: none ships
        pretrained.export_runs(tmp_path / "runs" / "none", tmp_path / "runs" / "none", {}, tmp_path / "x")
    full = pretrained.export_runs(tmp_path / "runs" / "none", None, {"what": "test"}, tmp_path / "f32")
    half = pretrained.export_runs(tmp_path / "runs" / "none", None, {"what": "test"}, tmp_path / "f16",
                                  weights_dtype="float16")
    assert pretrained.pretrained_runs(tmp_path / "f16") == {"policy": tmp_path / "f16" / "policy"}
    assert half < 0.6 * full
    stored = load_checkpoint(latest_checkpoint(tmp_path / "f16" / "policy")).params
    assert {str(leaf.dtype) for leaf in jax.tree.leaves(stored)} == {"float16"}
    env = ConavEnv(tiny_data, "val", EnvConfig(sensor=SensorConfig(resolution=(16, 64), materials="instance")))
    agent = make_agent("conav", env, tmp_path / "f16" / "policy")
    assert agent.intention_source == "none"
    # Loading widens the stored weights exactly: float32 values of the float16 ones.
    from conav_jax.envs.agents.policy import load_policy_run

    loaded, _, _ = load_policy_run(tmp_path / "f16" / "policy")
    for a, b in zip(jax.tree.leaves(loaded), jax.tree.leaves(params), strict=True):
        assert a.dtype == np.float32
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b).astype(np.float16).astype(np.float32))


def test_pretrained_flag_names_the_predictors_shipped_beside_a_policy(monkeypatch):
    shipped = {"policy": Path("/pkg/policy"), "intention": Path("/pkg/intention"), "trajectory": Path("/pkg/trajectory")}
    monkeypatch.setattr(pretrained, "pretrained_runs", lambda root=None: shipped)
    args = _eval_args("--agent", "conav", "--pretrained")
    _use_pretrained(args, ("conav",))
    assert (args.checkpoint, args.intention, args.trajectory) == ("/pkg/policy", "/pkg/intention", "/pkg/trajectory")



def test_int8_export_stores_the_largest_matrices_as_int8_and_the_rest_at_half_precision(tmp_path, monkeypatch):
    from conav_jax.checkpoints import quantize_int8

    rng = np.random.default_rng(2)
    params = {"visual": {"w": rng.normal(size=(512, 64)).astype(np.float32), "b": np.zeros(64, np.float32)},
              "head": {"w": rng.normal(size=(64, 8)).astype(np.float32)}, "count": np.arange(3, dtype=np.int32)}
    save_checkpoint(checkpoint_path(tmp_path / "runs" / "none", 1), params=params, opt_state=None, step=1,
                    config={"kind": "policy", "intention_run": None, "trajectory_run": None})
    monkeypatch.setattr(pretrained, "INT8_MIN_ENTRIES", 512 * 64)
    f16 = pretrained.export_runs(tmp_path / "runs" / "none", None, {}, tmp_path / "f16", weights_dtype="float16")
    i8 = pretrained.export_runs(tmp_path / "runs" / "none", None, {}, tmp_path / "i8", weights_dtype="int8")
    assert i8 < 0.6 * f16
    # Re-exporting a run exported at half precision (float16 leaves) quantises it too.
    again = pretrained.export_runs(tmp_path / "f16" / "policy", None, {}, tmp_path / "again", weights_dtype="int8")
    assert again == i8
    path = latest_checkpoint(tmp_path / "i8" / "policy")
    with zipfile.ZipFile(path) as zf:
        stored = {m[len("params/"):-len(".npy")]: np.lib.format.read_array(zf.open(m)).dtype
                  for m in zf.namelist() if m.startswith("params/")}
    assert stored == {"visual/w": np.int8, "visual/w/int8_scale": np.float32, "visual/b": np.float16,
                      "head/w": np.float16, "count": np.int32}
    loaded = load_checkpoint(path).params
    np.testing.assert_array_equal(np.asarray(loaded["visual"]["w"]), quantize_int8(params["visual"]["w"]).dequantized())
    np.testing.assert_array_equal(np.asarray(loaded["head"]["w"]), params["head"]["w"].astype(np.float16).astype(np.float32))
    # Without a template the int8 leaf loads as float32, the others as stored.
    assert {k: str(v.dtype) for k, v in loaded["visual"].items()} == {"w": "float32", "b": "float16"}
