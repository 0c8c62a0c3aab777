"""Baseline agents and the agent registry: jitted batches over mixed scenes, behaviour in the hall.

All rollouts share ONE compiled function: every baseline acts at every step and each rollout
applies its own agent's action, so one compile of the env step covers all four agents.
"""

import numpy as np
import pytest
from worlds import ROOM, make_split

from conav_jax.data.episodes import EpisodeSplit
from conav_jax.envs.agents.base import as_state_agent, row_title
from conav_jax.envs.agents.baselines import BaselineConfig
from conav_jax.envs.agents.registry import check_agent, make_agent
from conav_jax.envs.rollout import trace_step

BASELINES = ("random", "pioneer-drive", "follower", "objectgoal-planner")  # the velocity-commanded ones
T_ARRIVE, T_END = 120, 160  # the human walks 7.25 m from step 60 to 120 (1.2 m/s)
# Compile time dominates on a CPU: without LLVM optimisation and XLA's fusion emitters the
# rollouts compile several times faster (same results, slower to run).
FAST = {"xla_backend_optimization_level": 0, "xla_cpu_use_fusion_emitters": False}

# The hall with a partition at x = 5 from the south wall to y = 2.6: the way east is the 1.3 m
# gap at the north end.
PARTITION = {**ROOM, "name": "partition", "walls": ROOM["walls"] + [{"center_m": [5, 1.35, 1.25], "half_extents_m": [0.05, 1.25, 1.25]}]}


def _via(points, t_walk, t_arrive, t_end):
    """Human root positions (T, 2): standing at points[0] until t_walk, walking the polyline at
    constant speed to arrive at t_arrive, then standing at its end."""
    pts = np.asarray(points, np.float64)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.clip((np.arange(t_end + 1) - t_walk) / (t_arrive - t_walk), 0, 1) * seg.sum()
    cum = np.concatenate([[0], np.cumsum(seg)])
    return np.stack([np.interp(s, cum, pts[:, 0]), np.interp(s, cum, pts[:, 1])], -1).astype(np.float32)


def _two_scene_split() -> EpisodeSplit:
    starts = [(2.5, 3.0, 0.0), (3.0, 1.0, np.pi / 2)]
    hall = make_split(starts, t_arrive=T_ARRIVE, t_end=T_END)
    stand_a, stand_b = hall.navs[0].stand_poses[0, :2], hall.navs[0].stand_poses[1, :2]
    around = _via([stand_a, (5.0, 3.25), stand_b], T_ARRIVE // 2, T_ARRIVE, T_END)
    part = make_split([(2.5, 3.0, 0.0), (2.0, 1.0, 0.0)], human_xy=[around, around], t_arrive=T_ARRIVE, t_end=T_END, scene=PARTITION)
    episodes = {k: np.concatenate([hall.episodes[k], part.episodes[k]]) for k in hall.episodes}
    episodes["scene_index"] = np.array([0, 0, 1, 1], np.int32)
    return EpisodeSplit("test", {}, hall.scenes + part.scenes, hall.navs + part.navs, episodes, hall.config)


@pytest.fixture(scope="module")
def runs():
    """Every baseline on every episode (2 hall + 2 partition): poses (R, T+1, 3), actions
    (R, T, 2) and final metrics of R = 4 agents x 4 episodes rollouts, agent-major."""
    import jax
    import jax.numpy as jnp

    from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig

    env = ConavEnv(episodes=_two_scene_split(), config=EnvConfig(sensor=SensorConfig(resolution=(8, 32))))
    agents = [as_state_agent(make_agent(name, env)) for name in BASELINES]

    def start(episode, key):
        state = env.reset_to_episode(key, episode)
        return state, tuple(a.init(key, state) for a in agents)

    def one(begin, which, key):
        def body(c, k):
            state, carries = c
            outs = [a.act(state, cr, k) for a, cr in zip(agents, carries)]
            action = jnp.stack([o[0] for o in outs])[which]
            nxt = env.step(state, action)
            return (nxt, tuple(o[1] for o in outs)), (nxt.pipeline_state.qpos, action, trace_step(nxt, action).wall_contact)

        (state, _), (poses, actions, walls) = jax.lax.scan(body, begin, jax.random.split(key, T_END))
        return jnp.concatenate([begin[0].pipeline_state.qpos[None], poses]), actions, {**state.metrics, "wall_contact": walls}

    def run(episodes, which, keys):
        # The start vmapped on its own, as envs.rollout's rollouts do: every carry leaf enters the
        # scan batched (a partly unbatched carry has vmap batch the scan's body, the whole env
        # step, again until the batched leaves settle).
        return jax.vmap(one)(jax.vmap(start)(episodes, keys), which, keys)

    n = env.num_episodes
    episodes = jnp.tile(jnp.arange(n, dtype=jnp.int32), len(agents))
    which = jnp.repeat(jnp.arange(len(agents)), n)
    out = jax.jit(run, compiler_options=FAST)(episodes, which, jax.random.split(jax.random.PRNGKey(0), len(episodes)))
    poses, actions, metrics = jax.tree.map(np.asarray, out)
    return env, poses, actions, metrics


def _sel(runs, agent, episode):
    """(poses (T+1, 3), actions (T, 2), final metrics as floats plus "wall_contact" (T,) per step)."""
    _, poses, actions, metrics = runs
    r = BASELINES.index(agent) * 4 + episode
    return poses[r], actions[r], {k: float(v[r]) if v[r].ndim == 0 else v[r] for k, v in metrics.items()}


def test_baselines_run_jitted_over_mixed_scenes_with_bounded_actions(runs):
    env, poses, actions, _ = runs
    assert set(np.asarray(env.bank.scene_index).tolist()) == {0, 1}
    assert np.isfinite(actions).all() and np.isfinite(poses).all()
    assert (np.abs(actions) <= 1.0).all()
    rand = actions[: 4]  # the random agent's rollouts
    assert np.abs(rand).mean() > 0.3 and np.std(rand) > 0.3  # uniform in [-1, 1]: mean |a| = 0.5


def test_objectgoal_reaches_the_goal_before_the_human_in_the_hall(runs):
    _, _, m = _sel(runs, "objectgoal-planner", 0)
    assert 0 <= m["t_reach"] <= T_ARRIVE and m["collided_before_reach"] == 0.0
    assert m["wall_contact"][: int(m["t_reach"])].sum() == 0.0  # no wall touched on the way


def test_objectgoal_goes_round_the_partition(runs):
    poses, _, m = _sel(runs, "objectgoal-planner", 3)  # starts south-west of the partition
    assert 0 <= m["t_reach"] <= T_ARRIVE
    crossing = poses[np.argmax(poses[:, 0] > 5.0), :2]
    assert crossing[1] > 2.6  # it crossed x = 5 through the gap north of the partition


def test_driving_pioneer_waits_for_the_human_then_reaches_the_goal(runs):
    for episode in range(4):
        poses, _, m = _sel(runs, "pioneer-drive", episode)
        # While the human does activity A (until step 60) there is no motion to extrapolate.
        assert np.abs(poses[:55] - poses[0]).max() < 1e-3
        # Then it heads for the table; it drives no faster than the human walks, on the same
        # line, so it arrives after the human and may brush them (it does not avoid people).
        assert 0 <= m["t_reach"] <= T_END


def test_follower_stays_about_a_metre_behind_the_human(runs):
    env = runs[0]
    for episode in (0, 2):  # the open hall and round the partition
        poses, _, m = _sel(runs, "follower", episode)
        human = np.asarray(env.bank.root_xy[episode])[: T_END + 1]
        gap = np.linalg.norm(poses[:, :2] - human, axis=1)
        assert gap[-1] < 1.5  # caught up with the human at the goal
        assert gap[T_ARRIVE:].min() > BaselineConfig().follow_distance_m - 0.2  # and keeps its distance
        assert m["collided"] == 0.0  # it backs off when the walking human comes at it


def test_unknown_agent_names_the_choices():
    with pytest.raises(ValueError, match=r"unknown agent 'nope'; choose from random, pioneer"):
        check_agent("nope")


def test_learned_agents_need_an_existing_run_dir(tmp_path):
    for name in ("conav", "ppo"):
        with pytest.raises(ValueError, match=f"agent '{name}' needs a trained run: pass its checkpoint"):
            check_agent(name, None)
        with pytest.raises(ValueError, match=f"checkpoint run directory not found for agent '{name}'"):
            check_agent(name, tmp_path / "missing")


def test_every_agent_names_what_it_is_given(runs):
    env = runs[0]
    given = {n: make_agent(n, env) for n in BASELINES + ("expert",)}
    assert {n: (a.intention_source, a.privileged) for n, a in given.items()} == {
        "random": ("none", ()),
        "pioneer-drive": ("none", ("candidate goal points", "oracle map")),
        "follower": ("none", ("oracle map",)),
        "objectgoal-planner": ("none", ("oracle goal category", "oracle map")),
        "expert": ("none", ("oracle goal point", "oracle map", "future human positions", "human activity phase")),
    }
    assert row_title(given["objectgoal-planner"]) == "Object-goal planner (oracle goal category + oracle map)"
    assert row_title(given["random"]) == "Random Agent"
    with pytest.raises(ValueError, match="reads no intention inputs"):
        make_agent("pioneer", env, ground_truth=True)


def test_the_pioneer_is_put_at_the_goal_once_the_human_walks_and_first_reaches_it(runs):
    from conav_jax.envs.rollout import evaluate

    env = runs[0]
    pioneer = make_agent("pioneer", env)
    assert pioneer.action_size == 3 and pioneer.privileged == ("candidate goal points", "pose set by an oracle pathfinder")
    m = evaluate(env, pioneer, batch=4, compiler_options=FAST)
    # It stands still through activity A (until step 60), then the human's heading names the
    # table within a second or so: put there at once, it is first, long before the human arrives
    # at step 120.
    assert (m["t_reach"] > 60).all() and (m["t_reach"] < 80).all(), m["t_reach"]
    assert (m["path_length_m"] > 3.0).all()  # the oracle's moves count in its path
