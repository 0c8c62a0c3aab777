"""`conav demo`'s stages on the `demo` preset (the paper preset's apartments, activities and
walks in a few scenes: conav_jax.data.presets), as the `conav` command lines a user would type
(the command line runs them one after another and prints each).

generate -> [train intention -> train trajectory -> train the policy (live imitation)] ->
evaluate every agent (report, plots) -> one rerun recording.

By default the evaluation and the recording drive the CoNav agent with the policy shipped with
the package (`--pretrained`, trained on the paper preset: the evaluation renders the panorama it
was trained on, conav_jax/pretrained/PROVENANCE.json), and nothing is trained: a newcomer sees
the agents at work in a few minutes. `train=True` adds the training stages, the whole pipeline:
a hundred updates (25,600 env timesteps) show it but make no policy that reaches the goal;
`pretrained=False` evaluates the demo's own policy (and so trains it).
"""

from __future__ import annotations

from pathlib import Path

DEMO_PRESET = "demo"  # conav_jax.data.presets: paper-like episodes, small enough for a CPU


def demo_commands(out: Path, seed: int, resolution: str, pretrained: bool = True,
                  train: bool = False) -> list[list[str]]:
    """The demo's `conav` argument lists, writing under `out` (data/, runs/, eval/, episode0.rrd):
    the training stages only with `train` or without `pretrained` (whose agent they train)."""
    data, runs = out / "data", out / "runs"
    quick = ["--log-every", "25", "--no-progress"]
    conav = ["--pretrained"] if pretrained else ["--checkpoint", str(runs / "policy")]
    generate = [["generate", "--preset", DEMO_PRESET, "--out", str(data), "--seed", str(seed)]]
    training = [
        ["train", "intention", "--data", str(data), "--out", str(runs / "intention"), "--resolution", resolution, "--steps", "100",
         "--batch", "16", "--val-every", "100", "--ckpt-every", "100", "--seed", str(seed), *quick],
        ["train", "trajectory", "--data", str(data), "--out", str(runs / "trajectory"), "--steps", "200",
         "--batch", "64", "--val-every", "200", "--ckpt-every", "200", "--seed", str(seed), *quick],
        # Live imitation: one compiled iteration, so more updates cost seconds, not compiles.
        ["train", "live", "--data", str(data), "--out", str(runs / "policy"), "--intention", str(runs / "intention"),
         "--trajectory", str(runs / "trajectory"), "--resolution", resolution, "--lanes", "16", "--window-steps", "16",
         "--iterations", "100", "--warmup-iterations", "10", "--ckpt-every", "100", "--seed", str(seed), *quick],
    ]
    evaluation = [
        ["eval", "--data", str(data), "--split", "val", "--agent", "random,follower,objectgoal-planner,pioneer,expert,conav",
         *conav, "--seed", str(seed), "--out", str(out / "eval")],
        ["view", "--data", str(data), "--split", "val", "--episode", "0", "--agent", "conav", *conav,
         "--out", str(out / "episode0.rrd")],
    ]
    return generate + (training if train or not pretrained else []) + evaluation
