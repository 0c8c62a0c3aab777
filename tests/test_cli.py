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

    commands = demo_commands(tmp_path, seed=0, resolution="16x64")
    parsed = {tuple(argv[:2]): build_parser().parse_args(argv) for argv in commands}
    assert tuple(parsed[("train", "intention")].resolution) == tuple(parsed[("train", "policy")].resolution) == (16, 64)


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
    stages = demo_commands(tmp_path / "demo", args.seed, "x".join(map(str, args.resolution)), args.pretrained)
    assert events == [x for argv in stages for x in ("clear", tuple(argv))]
    events.clear()
    args = cli.build_parser().parse_args(["reproduce", "--preset", "tiny", "--out", str(tmp_path / "r"), "--stage",
                                          "generate"])
    cli.reproduce.run(args)
    assert events[0] == "clear" and events[1][0] == "generate"


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
    assert proc.stdout.strip() == "[generate] to run"
    assert "Traceback" not in proc.stderr and "BrokenPipeError" not in proc.stderr
