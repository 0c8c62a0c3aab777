"""conav_jax.provenance: the commit, dirtiness, JAX version and device recorded beside every
run and evaluation."""

import subprocess

import jax
import pytest

from conav_jax.provenance import UNKNOWN, git_state, provenance


def _git(repo, *args):
    subprocess.run(["git", "-C", str(repo), *args], check=True, capture_output=True)


def test_git_state_names_the_commit_and_sees_uncommitted_changes(tmp_path):
    _git(tmp_path, "init", "-q")
    (tmp_path / "a.txt").write_text("one")
    _git(tmp_path, "add", "a.txt")
    _git(tmp_path, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "one")
    head = subprocess.run(["git", "-C", str(tmp_path), "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    assert git_state.__wrapped__(tmp_path) == (head, False)
    (tmp_path / "a.txt").write_text("two")
    assert git_state.__wrapped__(tmp_path) == (head, True)


def test_git_state_outside_a_checkout_is_unknown(tmp_path):
    assert git_state.__wrapped__(tmp_path) == (UNKNOWN, None)


def test_provenance_records_jax_device_and_settings():
    block = provenance(caster="fast", resolution=[8, 32])
    assert block["jax"] == jax.__version__ and block["platform"] == jax.devices()[0].platform
    assert block["device_count"] == len(jax.devices())
    assert block["caster"] == "fast" and block["resolution"] == [8, 32]
    assert set(block) >= {"commit", "dirty"}
    with pytest.raises(ValueError, match="commit"):
        provenance(commit="made up")


def test_a_copy_of_the_tree_names_its_commit_through_the_environment(tmp_path, monkeypatch):
    monkeypatch.setenv("CONAV_COMMIT", "abc1234")
    assert git_state.__wrapped__(tmp_path) == ("abc1234", None)  # its own git state, if any, is not this code's


def test_every_trainers_run_config_records_provenance():
    from conav_jax.models.perceiver import PerceiverConfig
    from conav_jax.models.policy import PolicyConfig
    from conav_jax.models.trajectory import TrajectoryConfig
    from conav_jax.nav.expert import ExpertConfig
    from conav_jax.provenance import PROVENANCE_KEY
    from conav_jax.train import intention, policy, trajectory
    from conav_jax.train.policy import ImitationConfig
    from conav_jax.train.trajectory import TrajectoryDataConfig

    data = intention.IntentionDataConfig(resolution=(16, 64))
    configs = {"intention": intention.run_config(PerceiverConfig(), data, "hash", 1.0, 1.2),
               "trajectory": trajectory.run_config(TrajectoryConfig(), TrajectoryDataConfig(), "hash"),
               "policy": policy.run_config(PolicyConfig(resolution=(16, 64)), ImitationConfig(), ExpertConfig(), "hash",
                                           None, None)}
    for kind, config in configs.items():
        block = config[PROVENANCE_KEY]
        assert {"commit", "dirty", "jax", "device"} <= set(block), kind
    assert configs["intention"][PROVENANCE_KEY]["resolution"] == [16, 64]
    assert configs["policy"][PROVENANCE_KEY]["encoder"] == "conv"


def test_the_source_hash_follows_every_module_and_the_provenance_block_carries_it(tmp_path, monkeypatch):
    from conav_jax.provenance import code_hash, source_hash

    root = tmp_path / "fakecode"
    (root / "sub").mkdir(parents=True)
    for path, text in ((root / "__init__.py", ""), (root / "a.py", "A = 1\n"), (root / "sub" / "__init__.py", ""),
                       (root / "sub" / "b.py", "B = 2\n")):
        path.write_text(text)
    monkeypatch.syspath_prepend(str(tmp_path))
    before = source_hash(("fakecode",))
    assert source_hash(("fakecode",)) == before and len(before) == 16
    (root / "sub" / "b.py").write_text("B = 3\n")  # a module of a subpackage
    assert source_hash(("fakecode",)) != before
    (root / "sub" / "b.py").write_text("B = 2\n")
    (root / "sub" / "c.py").write_text("")  # a module added
    assert source_hash(("fakecode",)) != before
    assert provenance()["code"] == code_hash()
    with pytest.raises(ValueError, match="code"):
        provenance(code="made up")
