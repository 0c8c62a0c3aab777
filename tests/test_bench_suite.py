"""`conav bench suite`: BENCHMARKS.md's headline benchmarks run in turn, appended to one file, resumable."""

import json

import pytest

from conav_jax.eval.cli import bench_suite as bs


def test_the_suite_appends_each_result_with_its_command_and_commit_and_resumes(tmp_path):
    out = tmp_path / "suite.jsonl"
    data = {"SMALL": "/d/small", "PAPER": "/d/paper", "DEMO": "/d/demo"}
    calls = []

    def runner(argv):
        calls.append(argv)
        if "--encoder" in argv and argv[argv.index("--encoder") + 1] == "conv":
            return 1, "", "Traceback ...\nRuntimeError: out of memory\n"
        if argv[3] == "live":
            return 0, "progress text only\n", ""
        return 0, 'warming up\n{"batch": 1024, "rate": 5.0}\n{"batch": 256, "rate": 2.0}\n', ""

    names = ["sim_32x128", "policy_update_patch", "policy_update_conv", "live_gt_all"]
    outcome = bs.run_suite(names, data, out, runner=runner, say=lambda _: None)
    assert outcome == {"sim_32x128": "ran", "policy_update_patch": "ran", "policy_update_conv": "failed",
                       "live_gt_all": "failed"}
    assert calls[0] == ["--compile-cache", "off", "bench", "sim", "--data", "/d/small", "--split", "val", "--json",
                        "--steps", "10", "--repeats", "3", "--resolution", "32x128", "--batch", "32768"]
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert [r["suite"] for r in records] == ["sim_32x128"] * 2 + ["policy_update_patch"] * 2 + [
        "policy_update_conv", "live_gt_all"]
    assert records[0]["rate"] == 5.0 and records[1]["batch"] == 256
    assert records[0]["command"].startswith("conav --compile-cache off bench sim --data /d/small")
    assert records[0]["commit"] and "dirty" in records[0]
    assert records[4]["error"] == "exit status 1" and "out of memory" in records[4]["stderr_tail"]
    assert records[5]["error"] == "no JSON line printed"
    # Run again: what finished is skipped, what failed is tried again.
    calls.clear()
    outcome = bs.run_suite(names, data, out, runner=runner, say=lambda _: None)
    assert outcome["sim_32x128"] == outcome["policy_update_patch"] == "skipped"
    assert [c[3] for c in calls] == ["train", "live"]


def test_the_suite_refuses_unknown_benchmarks_and_missing_data_before_running_any(tmp_path):
    ran = []
    with pytest.raises(ValueError, match="reads the PAPER dataset"):
        bs.run_suite(["sim_32x128", "sweep_pioneer_drive"], {"SMALL": "s"}, tmp_path / "o.jsonl",
                     runner=lambda argv: ran.append(argv) or (0, "{}", ""))
    assert bs.suite_command("sim_32x128", {"SMALL": "/my data/small"})[5] == "/my data/small"  # one argument
    with pytest.raises(ValueError, match="no benchmark 'sim' in the suite"):
        bs.suite_command("sim", {})
    assert not ran and not (tmp_path / "o.jsonl").exists()


def test_each_benchmark_runs_the_command_line_in_a_fresh_process(tmp_path, monkeypatch):
    # Run where a checkout's `conav_jax/` source folder lies: the process still finds the package.
    (tmp_path / "conav_jax").mkdir()
    (tmp_path / "conav_jax" / "__init__.py").write_text("")
    monkeypatch.chdir(tmp_path)
    rc, stdout, _ = bs.run_in_process_of_its_own(["bench", "suite", "--out", "unused.jsonl", "--only", "sim_32x128",
                                                  "--small", "SMALL", "--dry-run"])
    assert rc == 0 and "sim_32x128: conav --compile-cache off bench sim --data SMALL" in stdout
