"""The public API (conav_jax.make_env, Agent, evaluate, OBSERVATIONS): the README's snippet runs,
an agent sees exactly the observation keys it declares (privileged ones only when it declares
their input), ConavEnv.step takes velocities only, user agents load from "module:factory", and
the API and the command line import beside a user's own `train.py`, `eval.py` and `envs/`."""

import json
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from worlds import make_split

import conav_jax
from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
from conav_jax.envs.agents.base import GROUND_TRUTH_INTENTIONS, row_title, switch_agent
from conav_jax.envs.agents.registry import make_agent
from conav_jax.envs.observations import OBSERVATION_KEYS, PRIVILEGED_KEYS, SENSOR_KEYS
from conav_jax.envs.rollout import make_param_rollout

ROOT = Path(__file__).resolve().parents[1]
KEY = jax.random.PRNGKey(0)


@pytest.fixture(scope="module")
def hall():
    split = make_split([(2.5, 2.0, 0.0), (7.5, 3.0, np.pi)])
    return ConavEnv(episodes=split, config=EnvConfig(sensor=SensorConfig(resolution=(8, 32))))


def _snippet() -> str:
    text = (ROOT / "README.md").read_text()
    found = re.search(r"<!-- snippet: evaluate-your-own-agent -->\s*```python\n(.*?)```\s*<!-- /snippet -->", text, re.S)
    assert found, "README.md holds no evaluate-your-own-agent snippet"
    return found.group(1)


def test_readme_snippet_evaluates_an_agent(tiny_data, tmp_path, capsys, monkeypatch):
    from conav_jax.eval import api

    code = _snippet().replace('"data/tiny"', repr(str(tiny_data)))
    code = re.sub(r"resolution=\(\d+, \d+\)", "resolution=(8, 32)", code)
    assert repr(str(tiny_data)) in code
    agents, evaluate = [], api.evaluate
    monkeypatch.setattr(api, "evaluate", lambda env, agent, **kw: agents.append(agent) or evaluate(env, agent, **kw))
    scope = {}
    exec(compile(code, "README.md", "exec"), scope)
    env, results = scope["env"], scope["results"]
    assert sorted(results.metrics["episode"]) == list(range(env.num_episodes)) == [r["episode"] for r in results.records]
    fasr = results.summary["FASR"]
    assert 0.0 <= fasr["lo"] <= fasr["value"] <= fasr["hi"] <= 100.0
    assert repr(fasr["value"]) in capsys.readouterr().out
    # Again with out_dir (the compiled rollout reused): the same numbers, and the files of a row.
    (agent,) = agents
    again = evaluate(env, agent, seed=0, out_dir=tmp_path)
    assert again.summary == results.summary
    report = (tmp_path / "report.md").read_text()
    assert agent.title in report and "FASR" in report and (tmp_path / "metrics.json").exists()
    assert len((tmp_path / f"episodes_{agent.title}.csv").read_text().splitlines()) == env.num_episodes + 1
    # The keys it reads (none declared: every sensor) are recorded with the row.
    assert json.loads((tmp_path / "metrics.json").read_text())["agents"][agent.title]["reads"] == list(SENSOR_KEYS)
    assert f"| {agent.title} | none | none | {', '.join(f'`{k}`' for k in SENSOR_KEYS)} |" in report


def test_evaluate_writes_the_files_conav_eval_writes(tiny_data, tmp_path):
    from conav_jax.eval.cli import main

    cli, api = tmp_path / "cli", tmp_path / "api"
    assert main(["--compile-cache", "off", "eval", "--data", str(tiny_data), "--agent", "pioneer-drive", "--episodes", "3",
                 "--batch", "4", "--resolution", "8x32", "--seed", "1", "--out", str(cli)]) == 0
    env = conav_jax.make_env(str(tiny_data), "val", resolution=(8, 32), max_episodes=3)
    results = conav_jax.evaluate(env, make_agent("pioneer-drive", env), batch=4, seed=1, out_dir=api)
    assert results.out_dir == api and results.agent["reads"] == ["human_history"]
    files = sorted(p.name for p in cli.iterdir())
    assert files == sorted(p.name for p in api.iterdir())
    assert {"report.md", "metrics.json", "episodes_pioneer-drive.csv", "map_pioneer-drive.png"} <= set(files)
    for name in ("report.md", "metrics.json", "episodes_pioneer-drive.csv"):
        assert (api / name).read_text() == (cli / name).read_text(), name
    doc = json.loads((api / "metrics.json").read_text())
    assert doc["content_hash"] == env.split.content_hash and doc["agents"]["pioneer-drive"]["reads"] == ["human_history"]
    report = (api / "report.md").read_text()
    assert f"content hash {env.split.content_hash[:16]}" in report
    assert "| Pioneer Agent, driving (candidate goal points + oracle map) | none | candidate goal points, oracle map | " \
           "`human_history`, the simulator's state |" in report


def test_the_api_and_command_line_import_beside_a_users_own_modules(tmp_path):
    for name in ("train.py", "eval.py", "envs/__init__.py"):
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_text(f"raise RuntimeError('the user's own {name} was imported')\n")
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    code = "import conav_jax; conav_jax.make_env, conav_jax.evaluate, conav_jax.OBSERVATIONS; import conav_jax.eval.cli"
    for cmd in ([sys.executable, "-c", code], [str(Path(sys.executable).parent / "conav"), "--help"]):
        proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr


def test_agents_of_one_program_share_a_compiled_rollout(hall, monkeypatch):
    """evaluate takes an agent's weights as its rollout's arguments: two agents of one program
    and other weights compile once, and each gets, bit for bit, the numbers of a rollout
    compiled around its own weights."""
    from conav_jax.eval import api
    from conav_jax.envs.rollout import make_evaluator

    def steering(seed):  # an affine map of GPS/compass to velocities, its weights closed over
        w = jax.random.normal(jax.random.PRNGKey(seed), (2, 4))
        return conav_jax.Agent(f"steering {seed}", lambda key, obs: (),
                               lambda carry, obs, key: (carry, jnp.tanh(w[:, :3] @ obs["gps_compass"] + w[:, 3])),
                               reads=("gps_compass",))

    built = []
    monkeypatch.setattr(api, "make_evaluator", lambda *a, **k: built.append(a) or make_evaluator(*a, **k))
    first, second = (conav_jax.evaluate(hall, steering(seed), seed=2) for seed in (1, 2))
    assert len(built) == 1
    assert not np.array_equal(first.metrics["path_length_m"], second.metrics["path_length_m"])
    closed = make_evaluator(hall, lambda _: steering(2), 256, 2)(None, None)
    assert set(closed) == set(second.metrics)
    for k, v in closed.items():
        np.testing.assert_array_equal(second.metrics[k], v, err_msg=k)


def test_step_refuses_anything_but_velocities(hall):
    start = jax.eval_shape(lambda: hall.reset_to_episode(KEY, 0, observe=False))
    for shape in ((3,), (6,), (1, 2)):
        with pytest.raises(ValueError, match=r"action must have shape \(2,\).*step_to_pose"):
            hall.step(start, jnp.zeros(shape))
    with pytest.raises(ValueError, match=r"step_to_pose takes a pose \(3,\)"):
        hall.step_to_pose(start, jnp.zeros(2))  # an oracle's pose goes through its own method


def test_an_agent_sharing_a_rollout_with_the_pioneer_cannot_set_the_pose(hall):
    # The scripted agents share one rollout of mixed actions (the pioneer's poses, the others'
    # velocities); what an agent declares, not the shape it returns, says which it gives.
    pioneer = make_agent("pioneer", hall)
    teleporter = conav_jax.Agent("teleporter", lambda key, obs: (), lambda carry, obs, key: (carry, jnp.zeros(3)))
    with pytest.raises(ValueError, match=r"'teleporter' declares actions of size 2 .*returned shape \(3,\)"):
        _trace(hall, lambda which: switch_agent([pioneer, teleporter], which), jnp.int32(1))
    _trace(hall, lambda which: switch_agent([pioneer, _spy("still")[0]], which), jnp.int32(1))  # velocities pass
    # Only a declared oracle mover's actions are poses; a group's mixed kind is no agent's own.
    mixed = switch_agent([pioneer, _spy("still")[0]], jnp.int32(0))
    with pytest.raises(ValueError, match="action_size is 2 .* or 3"):
        mixed._replace(privileged=()).check()


def _spy(title, **declared):
    """An Agent that stands still and records the observation keys init and act receive."""
    seen = {}

    def init(key, obs):
        seen["init"] = set(obs)
        return ()

    def act(carry, obs, key):
        seen["act"] = set(obs)
        return carry, jnp.zeros(2)

    return conav_jax.Agent(title, init, act, **declared), seen


def _trace(env, agent_fn, params=None):
    run = make_param_rollout(env, agent_fn, num_steps=2)
    jax.eval_shape(run, params, KEY, jnp.arange(2, dtype=jnp.int32))


def test_privileged_keys_reach_only_agents_that_declare_them(hall):
    blind, blind_seen = _spy("blind")
    told, told_seen = _spy("told", reads=("human_pos", "object_probs"), privileged=(GROUND_TRUTH_INTENTIONS,))
    _trace(hall, lambda which: switch_agent([blind, told], which), jnp.int32(0))  # one rollout serving both
    assert blind_seen["init"] == blind_seen["act"] == set(SENSOR_KEYS)
    assert told_seen["init"] == told_seen["act"] == {"human_pos", "object_probs"}
    assert row_title(told.check()) == "told (ground-truth intentions)" and row_title(blind.check()) == "blind"
    blind_seen.clear()
    _trace(hall, lambda _: blind)  # on its own, in an env whose brax observation holds the ground truth
    assert blind_seen["init"] == blind_seen["act"] == set(SENSOR_KEYS)
    sneaky, _ = _spy("sneaky", reads=("object_probs",))
    with pytest.raises(ValueError, match=r"sneaky.*object_probs \(privileged='ground-truth intentions'\)"):
        _trace(hall, lambda _: sneaky)
    with pytest.raises(ValueError, match="unknown observation key 'map'"):
        _trace(hall, lambda _: _spy("mapper", reads=("map",), privileged=("oracle map",))[0])


def test_observation_table_matches_the_envs_observations(hall):
    obs = jax.eval_shape(lambda: hall.observe(hall.reset_to_episode(KEY, 0, observe=False), OBSERVATION_KEYS)).obs
    shapes = conav_jax.observation_shapes(hall.config)
    assert set(obs) == {o.key for o in conav_jax.OBSERVATIONS} == set(shapes)
    for o in conav_jax.OBSERVATIONS:
        assert (obs[o.key].shape, obs[o.key].dtype) == (shapes[o.key], np.dtype(o.dtype)), o.key
    assert {k: o.privileged for k, o in zip(OBSERVATION_KEYS, conav_jax.OBSERVATIONS) if o.privileged} == PRIVILEGED_KEYS
    # brax's reset observes the sensors, and the ground truth only with intention_obs (training).
    assert set(jax.eval_shape(hall.reset, KEY).obs) == set(SENSOR_KEYS) | set(PRIVILEGED_KEYS)
    blind = ConavEnv(episodes=hall.split, config=EnvConfig(sensor=hall.config.sensor, intention_obs=False))
    assert set(jax.eval_shape(blind.reset, KEY).obs) == set(SENSOR_KEYS)


def test_user_agents_load_from_module_and_factory(hall, tmp_path, monkeypatch):
    (tmp_path / "my_agents.py").write_text(textwrap.dedent("""
        import jax.numpy as jnp
        import conav_jax

        def act(carry, obs, key):
            return carry, jnp.zeros(2)

        def still(env):
            return conav_jax.Agent("Standing still", lambda key, obs: (), act, reads=("gps_compass",))

        def told():
            return conav_jax.Agent("Told", lambda key, obs: (), act, reads=("object_probs",),
                                   privileged=("ground-truth intentions",))

        def not_an_agent(env):
            return "still"
    """))
    monkeypatch.syspath_prepend(str(tmp_path))
    still = make_agent("my_agents:still", hall)
    assert (still.title, still.name, still.reads) == ("Standing still", "Standing still", ("gps_compass",))
    assert row_title(make_agent("my_agents:told", hall)) == "Told (ground-truth intentions)"
    for name, match in (("my_agents:not_an_agent", "returned str, not a conav_jax.Agent"),
                        ("my_agents:missing", "has no 'missing'"),
                        ("no_such_module_here:factory", "cannot import module 'no_such_module_here'"),
                        ("my_agents:", "package.module:factory")):
        with pytest.raises(ValueError, match=match):
            make_agent(name, hall)
