"""envs.agents.goalnav and train.goalnav in the hand-built hall (8x32 panoramas): the object-goal
planner teaches through imitation's rollout and the goal image is recorded beside it; object-goal
and image-goal policies overfit it and then beat random in one jitted sweep; each agent names its
privileged inputs; the object-goal agent's category comes from the episode (oracle) or the
predictor's argmax, step by step (predicted); the image-goal agent's goal image is rendered at the
human's position; runs load through the registry and `conav eval --checkpoint AGENT=RUN,...`.

Two simulator programs are compiled for the whole module: the teacher's recording and one
evaluator running every agent (envs.agents.base.switch_agent)."""

import dataclasses
import functools
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from worlds import make_split

from conav_jax.checkpoints import checkpoint_path, save_checkpoint
from conav_jax.models import policy
from conav_jax.models.policy import PolicyConfig
from conav_jax.optim import adam
from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
from conav_jax.envs.conav_env import BankView
from conav_jax.envs.agents.base import row_title, switch_agent
from conav_jax.envs.agents.baselines import objectgoal_planner_agent, random_agent
from conav_jax.envs.agents.goalnav import (
    GOAL_IMAGE,
    goal_image_at,
    imagegoal_agent_from_params,
    objectgoal_agent_from_params,
)
from conav_jax.envs.agents.policy import load_policy_run, make_policy_step
from conav_jax.envs.agents.registry import make_agent
from conav_jax.envs.metrics import summarize
from conav_jax.envs.mjcf import UD
from conav_jax.envs.rollout import make_evaluator
from conav_jax.train import imitation as im
from conav_jax.train.goalnav import (imagenav_model, imagenav_task, objectnav_model, objectnav_task,
                                     train_objectnav_live)
from conav_jax.train.live import STEPS, LiveConfig, iteration_key, make_iteration, train_live
from conav_jax.train.policy import ImitationConfig, task_run_config

FAST = {"xla_backend_optimization_level": 0}  # the small jits (as tests/test_imitation.py)
ENV_FAST = {**FAST, "xla_cpu_use_fusion_emitters": False}  # the teacher's rollout (as tests/test_imitation.py)
SMALL = PolicyConfig(resolution=(8, 32), conv_channels=(8, 8), conv_kernels=(3, 3), visual_dim=32, state_dim=16,
                     intention_dim=8, hidden=32, saliency_sectors=4, goal_conv_channels=(8, 8),
                     goal_conv_kernels=(3, 3), goal_dim=16)
OBJ = objectnav_model((8, 32), base=SMALL)
IMG = imagenav_model((8, 32), base=SMALL)
T_WALK, T_ARRIVE, T_END = 10, 20, 70  # the human walks the last 1.5 m to the table in steps 10-20
TABLE, FRIDGE = 4, 11  # the hall's object categories: the goal (object B) and activity A's
SEQ, BURN_IN = 16, 8


def _human_track() -> np.ndarray:
    """Root positions (T, 2): 1.5 m west of the table's standing point, walking there in steps
    T_WALK-T_ARRIVE, then standing there (doing activity B) facing the table, as the goal image
    was taken: from then on the human's view is the goal's."""
    stand = make_split([(3.5, 2.0, 0.0)]).navs[0].stand_poses[1, :2]
    frac = np.clip((np.arange(T_END + 1) - T_WALK) / (T_ARRIVE - T_WALK), 0.0, 1.0)[:, None]
    return (stand - [1.5, 0.0] + frac * [1.5, 0.0]).astype(np.float32)


@pytest.fixture(scope="module")
def hall():
    """Three starts 4-5 m from the table, roughly facing it; the teacher's rollouts (objectnav's
    planner, recording the imagenav goal image beside it: in the hall the only table is the
    goal, so both teachers agree) and the BC windows."""
    split = make_split([(3.5, 2.0, 0.0), (4.0, 2.9, 0.3), (3.0, 1.2, -0.3)], human_xy=[_human_track()] * 3,
                       t_arrive=T_ARRIVE, t_end=T_END)
    env = ConavEnv(episodes=split, config=EnvConfig(sensor=SensorConfig(resolution=(8, 32)), end_at_reach=True))
    rollout = jax.jit(im.make_rollout_fn(env, OBJ, teacher=objectnav_task().teacher(env),
                                         goal_obs=imagenav_task().goal_obs(env)), compiler_options=ENV_FAST)
    params = policy.init(jax.random.PRNGKey(0), OBJ)
    metrics, recs = jax.tree.map(np.asarray, rollout(params, jax.random.PRNGKey(0), jnp.arange(3, dtype=jnp.int32), 1.0))
    return SimpleNamespace(env=env, metrics=metrics, recs=recs, windows=im.sequences(recs, SEQ, BURN_IN))


def _fit(windows: dict, seed: int = 1, steps: int = 200) -> tuple[dict, dict]:
    """The object-goal and image-goal policies fitted to the same windows together (one compiled
    update, full-batch Adam on the sum of their bc_losses) -> ({kind: params}, {kind: losses})."""
    cfgs = {"objectnav": OBJ, "imagenav": IMG}
    opt = adam(3e-3)

    def loss(params):
        losses = {k: im.bc_loss(params[k], cfg, windows)[0] for k, cfg in cfgs.items()}
        return sum(losses.values()), losses

    # XLA's default optimisation: the updates run 3x faster than at FAST's level for 1.5 s of compile.
    @functools.partial(jax.jit, compiler_options={"xla_backend_optimization_level": 2})
    def update(params, state):
        (_, losses), grads = jax.value_and_grad(loss, has_aux=True)(params)
        params, state = opt.update(grads, state, params)
        return params, state, losses

    params = {k: policy.init(jax.random.PRNGKey(seed), cfg) for k, cfg in cfgs.items()}
    state, history = opt.init(params), []
    for _ in range(steps):
        params, state, losses = update(params, state)
        history.append(losses)
    history = jax.tree.map(lambda *x: np.asarray(x), *history)
    return params, history


@pytest.fixture(scope="module")
def trained(hall):
    params, losses = _fit(hall.windows)
    return SimpleNamespace(params=params, losses=losses)


def _category_predictor(first: int, then: int, switch_at: int = 2, privileged: tuple = ()):
    """A stand-in intention predictor naming object `first` for its first `switch_at` steps, then `then`."""
    return SimpleNamespace(
        init=lambda: jnp.int32(0),
        step=lambda carry, obs: (jax.nn.one_hot(0, 107), 0.9 * jax.nn.one_hot(jnp.where(carry < switch_at, first, then), 51)
                                 + 0.1 / 51, carry + 1),
        privileged=privileged,
    )


@pytest.fixture(scope="module")
def agents(hall, trained):
    env = hall.env
    return {
        "random": random_agent(env),
        "objectgoal-oracle": objectgoal_agent_from_params(trained.params["objectnav"], OBJ, env),
        "objectgoal-predicted": objectgoal_agent_from_params(trained.params["objectnav"], OBJ, env,
                                                              _category_predictor(TABLE, TABLE)),
        "imagegoal": imagegoal_agent_from_params(trained.params["imagenav"], IMG, env),
    }


def test_the_object_goal_planner_teaches_and_the_goal_image_is_recorded(hall):
    m, recs = hall.metrics, hall.recs
    assert (m["t_reach"] >= 0).all(), m["t_reach"]
    np.testing.assert_array_equal(recs.action, recs.label)  # beta = 1: the planner drives
    assert recs.obs[GOAL_IMAGE].dtype == np.uint8 and recs.obs[GOAL_IMAGE].shape == (3, T_END + 1, 8, 8, 3)
    np.testing.assert_array_equal(recs.obs["object_probs"].argmax(-1), TABLE)  # the goal category
    # The goal image is taken at the goal's standing pose, the human posed at the step.
    b = hall.env.bank
    stand = b.field_stand[0, b.field_b[0]]
    steps = np.array([0, T_ARRIVE])  # the human 1.5 m behind the camera, then where it is
    expected = jax.jit(jax.vmap(lambda t: goal_image_at(hall.env, 0, stand, t)))(steps)
    np.testing.assert_array_equal(recs.obs[GOAL_IMAGE][0, steps], np.round(np.asarray(expected) * 255).astype(np.uint8))
    assert (im.expand_obs(jax.tree.map(lambda x: x[:, :2], recs.obs))[GOAL_IMAGE] <= 1.0).all()


def test_the_object_goal_teacher_descends_to_the_nearest_instance_from_where_the_robot_is(hall):
    # Relabel the fridge a table: from near the fridge the nearest "table" is the fridge.
    b = hall.env.bank
    two_tables = SimpleNamespace(bank=dataclasses.replace(b, field_category=jnp.full_like(b.field_category, TABLE)),
                                 task=hall.env.task)
    two_tables.bank_view = BankView(two_tables)
    teacher = objectgoal_planner_agent(two_tables, replan=True)
    planner = objectgoal_planner_agent(two_tables)

    def state(x, yaw):
        return SimpleNamespace(info={"episode": jnp.int32(0)}, pipeline_state=SimpleNamespace(qpos=jnp.array([x, 2.0, yaw])))

    key = jax.random.PRNGKey(0)

    @jax.jit
    def run(x, yaw):
        start = planner.init(key, state(3.5, 0.0))
        (action, chosen), (_, kept) = (teacher.act(state(x, yaw), start, key), planner.act(state(x, yaw), start, key))
        return start, action, chosen, kept

    start, action, chosen, kept = jax.vmap(run)(jnp.array([2.0, 7.5]), jnp.array([np.pi, 0.0]))
    np.testing.assert_array_equal(start, 0)  # episode 0 starts at x = 3.5: the fridge is the nearer
    np.testing.assert_array_equal(chosen, [0, 1])  # near the fridge the fridge, near the table the table
    assert (action[:, 0] > 0.5).all()  # facing it: full speed ahead
    np.testing.assert_array_equal(kept, 0)  # the planner keeps its first choice


def test_both_policies_overfit_the_teacher(trained):
    for name, losses in trained.losses.items():
        assert losses[-1] < 0.05 * losses[0], (name, losses[::30])


def test_learned_agents_run_jitted_in_one_sweep_and_beat_random(hall, agents):
    names = list(agents)
    evaluator = make_evaluator(hall.env, lambda which: switch_agent(list(agents.values()), which), batch=3)
    results = {n: summarize(evaluator(jnp.int32(i))) for i, n in enumerate(names)}
    for name in ("objectgoal-oracle", "objectgoal-predicted", "imagegoal"):
        assert results[name]["RASR"] == 100.0, (name, results[name])
        assert results[name]["AS"] < results["random"]["AS"], (name, results[name], results["random"])
    assert results["random"]["RASR"] < 100.0, results["random"]


def test_every_goal_agent_names_what_it_is_given(agents):
    given = {n: (a.intention_source, a.privileged) for n, a in agents.items()}
    assert given == {
        "random": ("none", ()),
        "objectgoal-oracle": ("none", ("oracle goal category", "oracle segmentation")),
        "objectgoal-predicted": ("predicted", ("oracle segmentation",)),
        "imagegoal": ("none", ("goal image from the human's position",)),
    }
    assert row_title(agents["objectgoal-oracle"]) == "Object-goal agent (oracle goal category + oracle segmentation)"
    assert row_title(agents["imagegoal"]) == "Image-goal agent (goal image from the human's position)"
    no_saliency = dataclasses.replace(OBJ, object_saliency=False)
    blind = objectgoal_agent_from_params(policy.init(jax.random.PRNGKey(0), no_saliency), no_saliency, SimpleNamespace(bank=None, bank_view=None))
    assert blind.privileged == ("oracle goal category",)
    # A predictor that reads the segmentation (PerceiverConfig.seen_objects) makes even the
    # agent without the saliency channel list it.
    seg = ("oracle segmentation",)
    predicted = objectgoal_agent_from_params(policy.init(jax.random.PRNGKey(0), no_saliency), no_saliency, None,
                                             _category_predictor(TABLE, TABLE, privileged=seg))
    assert predicted.privileged == seg


def _fake_state(episode: int, t: int, category: int = FRIDGE):
    """A one-env state at step t of `episode` with a blank panorama and a wrong `object_probs`."""
    obs = {"rgbd": jnp.zeros((8, 32, 4)), "segmentation": jnp.full((8, 32), -1, jnp.int32), "gps_compass": jnp.zeros(3),
           "object_probs": jax.nn.one_hot(category, 51)}
    ud = jnp.zeros(len(UD)).at[UD["t"]].set(t)
    return SimpleNamespace(obs=obs, info={"episode": jnp.int32(episode)},
                           pipeline_state=SimpleNamespace(userdata=ud, qpos=jnp.array([4.0, 2.0, 0.0])))


def test_the_oracle_category_comes_from_the_episode(hall, trained, agents):
    params = trained.params["objectnav"]
    agent, state = agents["objectgoal-oracle"], _fake_state(0, 5, category=FRIDGE)
    action, _ = agent.act(state, agent.init(jax.random.PRNGKey(0), state), jax.random.PRNGKey(0))
    pol = make_policy_step(OBJ)
    table, fridge = (pol.step(params, {**state.obs, "object_probs": jax.nn.one_hot(c, 51)}, pol.init())[0]
                     for c in (TABLE, FRIDGE))
    np.testing.assert_allclose(action, table, atol=1e-6)  # the episode's object B, not the obs
    assert not np.allclose(table, fridge, atol=1e-5)


def test_the_predicted_category_is_the_predictors_argmax_every_step(trained):
    params = trained.params["objectnav"]
    agent = objectgoal_agent_from_params(params, OBJ, None, _category_predictor(FRIDGE, TABLE))
    pol = make_policy_step(OBJ)
    assert "object_probs" not in agent.reads  # the truth never reaches it
    carry, named = agent.init(jax.random.PRNGKey(0), {}), []
    for t in range(4):
        state = _fake_state(0, t, category=TABLE)
        carry, action = agent.act(carry, state.obs, jax.random.PRNGKey(t))
        one_hot = np.asarray(carry.predicted["object_probs"])
        named.append(int(one_hot.argmax()))
        assert one_hot.sum() == 1.0 and one_hot.max() == 1.0
        given, _ = pol.step(params, {**state.obs, "object_probs": jnp.asarray(one_hot)}, pol.init())
        if t == 0:
            np.testing.assert_allclose(action, given, atol=1e-6)
    assert named == [FRIDGE, FRIDGE, TABLE, TABLE]


def test_the_image_goal_agent_sees_an_image_rendered_at_the_humans_position(hall, agents, monkeypatch):
    env, agent, seen = hall.env, agents["imagegoal"], []

    def render_at(episode, pose, t):  # where the camera is put; a blank image (no render needed)
        seen.append((int(episode), np.asarray(pose), int(t)))
        return jnp.zeros((8, 32, 4)), jnp.zeros((8, 32), jnp.int32)

    monkeypatch.setattr(env, "render_at", render_at)
    b = env.bank
    for t in (0, T_ARRIVE):  # 1.5 m from the goal, then at it
        agent.act(_fake_state(2, t), agent.init(jax.random.PRNGKey(0), _fake_state(2, t)), jax.random.PRNGKey(0))
        episode, pose, at = seen[-1]
        assert (episode, at) == (2, t)
        np.testing.assert_allclose(pose[:2], b.root_xy[2, t], atol=1e-6)  # where the human is
        np.testing.assert_allclose(pose[2], b.root_yaw[2, t], atol=1e-6)  # facing their heading
    assert np.linalg.norm(seen[1][1][:2] - seen[0][1][:2]) > 1.0  # the human walked, the camera followed


def test_lifted_goal_agents_act_as_before_and_share_a_key(hall, trained, agents, monkeypatch):
    """The goal agents given privileged inputs (envs.agents.base.sensing_agent) lift their
    policy's weights: they act as before from them, and the same agent with other weights has
    the same key."""
    from conav_jax.envs.agents.lift import lift_agent

    env = hall.env
    lifted = {name: lift_agent(env, agents[name]) for name in ("objectgoal-oracle", "imagegoal")}
    halved = jax.tree.map(lambda x: 0.5 * x, trained.params["objectnav"])
    assert lift_agent(env, objectgoal_agent_from_params(halved, OBJ, env)).key == lifted["objectgoal-oracle"].key
    assert lifted["imagegoal"].key != lifted["objectgoal-oracle"].key
    monkeypatch.setattr(env, "render_at", lambda episode, pose, t: (jnp.full((8, 32, 4), 0.5),
                                                                    jnp.zeros((8, 32), jnp.int32)))
    key = jax.random.PRNGKey(0)
    for name, lift in lifted.items():
        agent, again = agents[name], lift.agent_fn(lift.params)
        assert again.reads == agent.reads and again.privileged == agent.privileged
        state = _fake_state(2, T_ARRIVE)
        state.obs = {k: state.obs[k] for k in agent.reads}  # what a rollout observes for it
        (action, carry), (want, want_carry) = (a.act(state, a.init(key, state), key) for a in (again, agent))
        np.testing.assert_array_equal(action, want, err_msg=name)
        for got, expected in zip(jax.tree.leaves(carry), jax.tree.leaves(want_carry)):
            np.testing.assert_array_equal(got, expected, err_msg=name)


def test_goal_runs_load_through_the_registry_and_eval_takes_a_run_per_agent(hall, trained, tmp_path, tiny_data):
    from conav_jax.eval.cli import parse_checkpoints
    from conav_jax.eval.sweep import plan_eval

    run_dirs = {}
    for task, cfg, kind in ((objectnav_task(), OBJ, "objectnav"), (imagenav_task(), IMG, "imagenav")):
        run_dirs[kind] = tmp_path / kind
        config = task_run_config(task, cfg, ImitationConfig(), "test")
        assert config["kind"] == kind and config["model"]["use_human_pos"] is False
        save_checkpoint(checkpoint_path(run_dirs[kind], 1), params=trained.params[kind], opt_state=None, config=config,
                        step=1, extra={"round": 0, "val": {}, "expert_val": {}})
    env = hall.env
    built = {name: make_agent(name, env, run_dirs["imagenav" if name == "imagegoal" else "objectnav"])
             for name in ("objectgoal-oracle", "imagegoal")}
    assert built["objectgoal-oracle"].privileged == ("oracle goal category", "oracle segmentation")
    assert built["imagegoal"].privileged == ("goal image from the human's position",)
    with pytest.raises(ValueError, match="pass intention_run"):
        make_agent("objectgoal-predicted", env, run_dirs["objectnav"])
    with pytest.raises(ValueError, match="objectgoal-oracle agent"):
        make_agent("objectgoal-predicted", env, run_dirs["objectnav"], ground_truth=True)
    with pytest.raises(ValueError, match="reads no intention inputs"):
        make_agent("objectgoal-oracle", env, run_dirs["objectnav"], ground_truth=True)
    with pytest.raises(ValueError, match="'objectnav' run, expected 'imagenav'"):
        make_agent("imagegoal", env, run_dirs["objectnav"])
    text = f"objectgoal-oracle={run_dirs['objectnav']},imagegoal={run_dirs['imagenav']}"
    plan = plan_eval(tiny_data, "val", ("random", "objectgoal-oracle", "imagegoal"), tmp_path / "eval",
                     checkpoint=parse_checkpoints(text))
    assert [plan.checkpoint_of(n) for n in plan.agents] == [None, str(run_dirs["objectnav"]), str(run_dirs["imagenav"])]
    assert plan.resolution == (8, 32)
    with pytest.raises(ValueError, match="not a learned agent of this evaluation"):
        plan_eval(tiny_data, "val", ("random", "imagegoal"), tmp_path / "eval", checkpoint=parse_checkpoints(text))


@pytest.mark.parametrize("model, flags", [("objectnav", []), ("objectnav", ["--no-object-saliency"]), ("imagenav", []),
                                          ("objectnav", ["--encoder", "patch", "--conv-dtype", "bfloat16"]),
                                          ("imagenav", ["--encoder", "patch", "--conv-dtype", "bfloat16"])])
def test_train_commands_build_the_baselines_networks(model, flags, monkeypatch, tmp_path):
    from conav_jax.eval.cli import build_parser
    from conav_jax.train import goalnav

    seen = {}

    def fake(data, out, cfg, net, imitation, **kw):
        seen.update(net=net, imitation=imitation, cfg=cfg)
        rates = {"FASR": 0, "RASR": 0, "CR": 0, "AS": 0}
        return SimpleNamespace(run_dir=out, val=rates, expert_val=rates)

    monkeypatch.setattr(goalnav, f"train_{model}_from_data", fake)
    args = build_parser().parse_args(["train", model, "--data", str(tmp_path), "--out", str(tmp_path / "run"),
                                      "--resolution", "16x64", "--steps", "700", "--dagger-rounds", "2", "--dagger-beta", "0.5",
                                      *flags])
    assert args.func(args) == 0
    net = seen["net"]
    assert net.resolution == (16, 64) and not net.use_human_pos and not net.use_activity and not net.use_trajectory
    assert (net.use_object, net.goal_image) == ((True, False) if model == "objectnav" else (False, True))
    assert net.uses_saliency is (model == "objectnav" and "--no-object-saliency" not in flags)
    # The CoNav policy's panorama CNN flags reach the baselines' networks.
    from conav_jax.models.policy import encoder_name

    assert (encoder_name(net), net.conv_dtype) == (("patch", "bfloat16") if "--encoder" in flags else ("conv", "float32"))
    assert seen["cfg"].steps == 700 and (seen["imitation"].dagger_rounds, seen["imitation"].dagger_beta) == (2, 0.5)


def test_train_live_builds_the_object_goal_baseline(monkeypatch, tmp_path):
    """`conav train live --baseline objectnav` trains the object-goal network with the live
    flags, and refuses the CoNav policy's intention flags."""
    from conav_jax.eval.cli import build_parser
    from conav_jax.train import goalnav

    seen = {}

    def fake(data, out, model, live, **kw):
        seen.update(model=model, live=live)
        return SimpleNamespace(run_dir=out, env_steps=1, episodes_started=1)

    monkeypatch.setattr(goalnav, "train_objectnav_live_from_data", fake)
    base = ["train", "live", "--data", str(tmp_path), "--out", str(tmp_path / "run"), "--resolution", "16x64",
            "--lanes", "64", "--iterations", "7", "--warmup-iterations", "0", "--baseline", "objectnav"]
    args = build_parser().parse_args(base + ["--encoder", "patch"])
    assert args.func(args) == 0
    net = seen["model"]
    assert net.resolution == (16, 64) and net.use_object and not (net.use_human_pos or net.use_activity
                                                                  or net.use_trajectory or net.goal_image)
    assert net.uses_saliency and net.visual_norm and seen["live"].lanes == 64 and seen["live"].iterations == 7
    for extra in (["--ground-truth-intentions"], ["--ablation", "none"], ["--intention", str(tmp_path)]):
        args = build_parser().parse_args(base + extra)
        with pytest.raises(ValueError, match=f"no {extra[0]}"):
            args.func(args)


LIVE = LiveConfig(lanes=2, window_steps=10, iterations=2, warmup_iterations=0, seed=1, ckpt_every=2, log_every=1)


def test_the_object_goal_agent_trains_live_on_the_planners_labels(hall, tmp_path):
    """The object-goal policy imitates the replanning planner in train.live's loop: with beta = 1
    every label is the planner's action on the state it was taken in, the lanes drive as it
    does, and the run is an objectnav run the object-goal agent loads; a goal-image task is
    refused before anything compiles."""
    with pytest.raises(ValueError, match="reads a goal image"):
        train_live(hall.env, IMG, LIVE, tmp_path / "img", task=imagenav_task(), progress=False)
    with pytest.raises(ValueError, match="not an object-goal policy"):
        train_objectnav_live(hall.env, IMG, LIVE, tmp_path / "img", progress=False)
    task = objectnav_task()
    assert objectnav_task().teacher == task.teacher != imagenav_task().teacher  # equal tasks share compiles
    result = train_live(hall.env, OBJ, LIVE, tmp_path / "obj", progress=False, compiler_options=ENV_FAST, task=task)
    assert result.env_steps == LIVE.iterations * LIVE.lanes * LIVE.window_steps
    agent = make_agent("objectgoal-oracle", hall.env, tmp_path / "obj")
    assert agent.privileged == ("oracle goal category", "oracle segmentation")
    _, _, config = load_policy_run(tmp_path / "obj", "objectnav")
    assert config["teacher"]["planner"] == "objectgoal-planner" and "expert" not in config
    with pytest.raises(ValueError, match="'objectnav' run, expected 'policy'"):
        load_policy_run(tmp_path / "obj")

    fns, iteration = make_iteration(hall.env, OBJ, LIVE, compiler_options=tuple(sorted(ENV_FAST.items())),
                                    teacher=objectnav_task().teacher)  # another task of the run's: its compile
    state = fns.init(policy.init(jax.random.PRNGKey(LIVE.seed), OBJ))
    _, metrics = iteration(state, iteration_key(LIVE.seed, 0))
    window = jax.device_get(metrics[STEPS])
    assert window.expert_acted.all()  # beta 1
    planner = objectgoal_planner_agent(hall.env, replan=True)

    @jax.jit
    def label(episode, pose):
        state = SimpleNamespace(info={"episode": episode}, pipeline_state=SimpleNamespace(qpos=pose))
        return planner.act(state, jnp.int32(0), jax.random.PRNGKey(0))[0]

    for lane in range(LIVE.lanes):
        for t in range(LIVE.window_steps):
            np.testing.assert_allclose(window.label[t, lane], label(window.episode[t, lane], window.pose[t, lane]),
                                       atol=1e-6)
    moved = np.linalg.norm(window.pose[-1, :, :2] - window.pose[0, :, :2], axis=-1)
    assert (moved > 0.3).all()  # the labels drove the lanes towards the table
