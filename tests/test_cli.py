"""The `conav` command line (eval/cli.py): a bad --data fails before anything is created under --out."""

import json


def test_train_policy_with_missing_data_leaves_no_run_directory(tmp_path, capsys):
    from eval.cli import main

    missing, out = tmp_path / "no_such_dataset", tmp_path / "run"
    rc = main(["train", "policy", "--data", str(missing), "--out", str(out)])
    assert rc != 0
    assert not out.exists()
    assert "dataset directory not found" in capsys.readouterr().err


def test_train_policy_with_an_edited_manifest_leaves_no_run_directory(tmp_path, tiny_data):
    import shutil

    from eval.cli import main

    data, out = tmp_path / "data", tmp_path / "run"
    shutil.copytree(tiny_data, data)
    m = json.loads((data / "manifest.json").read_text())
    m["splits"]["train"]["shards"][0]["sha256"] = "0" * 64
    (data / "manifest.json").write_text(json.dumps(m))
    assert main(["train", "policy", "--data", str(data), "--out", str(out)]) != 0
    assert not out.exists()
