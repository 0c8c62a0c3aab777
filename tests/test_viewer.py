"""`conav view`: a recorded episode written as .rrd and read back with rerun's own reader."""

from typing import NamedTuple

import numpy as np
import pytest

from conav_jax.eval import viewer


def _args(*argv):
    from conav_jax.eval.cli import build_parser

    return build_parser().parse_args(["view", *argv])


@pytest.fixture(scope="module")
def recording(tiny_data, tmp_path_factory):
    import rerun.chunk

    out = tmp_path_factory.mktemp("view") / "episode.rrd"
    args = _args("--data", str(tiny_data), "--episode", "1", "--agent", "objectgoal-planner", "--resolution", "8x32", "--out", str(out))
    assert args.func(args) == 0
    return rerun.chunk.RrdReader(str(out)).stream().collect()


def _entities(store) -> dict[str, str]:
    """entity path -> its summary line."""
    return {line.split()[0]: line for line in store.summary().splitlines()}


def test_recording_holds_scene_human_robot_panorama_and_intentions(recording):
    ents = _entities(recording)
    for path in (
        "/world/scene/floor",
        "/world/scene/walls",
        "/world/scene/labels",
        "/world/goal",
        "/world/goal/success_radius",
        "/world/human/path",
        "/world/human/joints",
        "/world/human/bones",
        "/world/robot",
        "/world/robot/body",
        "/world/robot_path",
        "/camera/rgb",
        "/camera/depth",
        "/camera/object_saliency/ground_truth",
        # a baseline predicts nothing: the ground truth is shown, and labelled so
        "/intention/ground_truth/activity/top5",
        "/intention/ground_truth/object/text",
        "/world/human/future_traj/ground_truth",
    ):
        assert path in ents, path
    assert any(p.startswith("/world/scene/furniture/") and "Mesh3D:vertex_positions" in line for p, line in ents.items())
    assert "static=True" in ents["/world/scene/walls"]
    for path in ("/world/human/joints", "/camera/rgb", "/world/robot"):
        assert "'step'" in ents[path] and "static=False" in ents[path]


def test_the_human_is_animated_over_the_whole_episode(recording, tiny_data):
    from conav_jax.data.episodes import load_split

    t_end = int(load_split(tiny_data, "val", max_episodes=2).episodes["t_end"][1])
    rows = int(_entities(recording)["/world/human/joints"].split("rows=")[1].split()[0])
    assert rows == t_end + 1


class _Carry(NamedTuple):
    lstm: tuple
    activity_probs: np.ndarray


def test_predictions_are_read_from_an_agents_carry():
    assert viewer.agent_predictions(()) == {}
    assert set(viewer.agent_predictions({"object_probs": 1, "future_traj": 2, "h": 3})) == {"object_probs", "future_traj"}
    assert set(viewer.agent_predictions(_Carry((), np.zeros(3)))) == {"activity_probs"}
    # The CoNav policy's carry holds what its predictors produced under `predicted`.
    from conav_jax.envs.agents.policy import PolicyCarry

    carry = PolicyCarry((), None, {"future_traj": np.zeros((5, 2))})
    assert set(viewer.agent_predictions(carry)) == {"future_traj"}


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--episode", "999"], r"episode must be in \[0, \d+\)"),
        (["--episode", "0", "--agent", "nope"], "unknown agent"),
        (["--episode", "0", "--out", "x.png"], "must name a .rrd file"),
    ],
)
def test_bad_input_is_rejected_before_recording(tiny_data, tmp_path, argv, message):
    base = ["--data", str(tiny_data), "--out", str(tmp_path / "v.rrd")]
    args = _args(*base, *argv)
    with pytest.raises(ValueError, match=message):
        args.func(args)


def test_the_summary_says_which_ground_truth_intentions_are_shown_only():
    sources = {"activity_probs": "ground_truth", "object_probs": "predicted", "future_traj": "ground_truth"}
    text = viewer.intentions_summary(sources, reads=("rgbd", "future_traj"))
    assert text == ("activity_probs ground_truth (shown, not read), object_probs predicted, "
                    "future_traj ground_truth")
    assert viewer.intentions_summary({}, reads=("rgbd",)) == "none"
