"""train.imitation, train.policy and envs.agents.policy in the simulator (the hand-built hall,
8x32 panoramas): the expert reaches the goal without touching the human, rollouts repeat bit
for bit for a seed, the policy overfits expert actions, DAgger aggregates the expert's labels
of the policy's own states, and policy_agent loads a run (rejecting wrong ones, refusing to
read ground truth unless asked), feeds the policy its predictors' outputs and runs in evaluate."""

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
from conav_jax.nav.expert import ExpertConfig, initial_carry
from conav_jax.optim import adam
from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
from conav_jax.envs.agents.expert import make_expert_step
from conav_jax.envs.agents.policy import make_policy_step, policy_agent, predictor_runs
from conav_jax.envs.metrics import summarize
from conav_jax.envs.mjcf import UD
from conav_jax.envs.rollout import evaluate
from conav_jax.train import imitation as im
from conav_jax.train.loop import TrainConfig
from conav_jax.train.policy import ImitationConfig, check_recordable, records_predictions, run_config, train_policy_from_data

# For the small jits (tests/conftest.py sets level 0 for every other jit too).
FAST = {"xla_backend_optimization_level": 0}
# For the programs that step or render the env, whose compiles dominate this file on a CPU:
# without XLA's fusion emitters they compile much faster (slower to run; float rounding may
# differ from the default's).
ENV_FAST = {**FAST, "xla_cpu_use_fusion_emitters": False}
SMALL = EnvConfig(sensor=SensorConfig(resolution=(8, 32)), end_at_reach=True)  # as training runs it
PCFG = PolicyConfig(
    resolution=(8, 32), conv_channels=(8, 8), conv_kernels=(3, 3), visual_dim=32, state_dim=16, intention_dim=8, hidden=32
)
T_ARRIVE, T_END = 140, 160  # the human walks from the fridge to the table in steps 70-140
SEQ, BURN_IN = 16, 8


def _head_on_track() -> np.ndarray:
    """A human walking west along the hall's centre line at 1.1 m/s, from the table to x = 1."""
    x = np.maximum(8.6 - 0.11 * np.arange(T_END + 1), 1.0)
    return np.stack([x, np.full_like(x, 2.0)], -1).astype(np.float32)


@pytest.fixture(scope="module")
def hall():
    """Episodes: 0 east of the human at the fridge; 1 at the east end, facing back west; 2 with
    the human walking head-on at the robot (`episodes`, what most tests run); 3 and 4 two more
    starts, the human at the fridge, for the recordings in batches (5 episodes in batches of 3,
    the second padded). One compiled rollout, of 3 lanes, serves every test."""
    starts = [(2.5, 2.0, 0.0), (7.5, 3.0, np.pi), (2.2, 2.0, 0.0), (5.0, 1.0, 1.0), (3.0, 3.0, -1.0)]
    default = make_split(starts[:1], t_arrive=T_ARRIVE, t_end=T_END).episodes["root_xy"][0]
    human_xy = [default, default, _head_on_track(), default, default]
    split = make_split(starts, human_xy=human_xy, t_arrive=T_ARRIVE, t_end=T_END)
    env = ConavEnv(episodes=split, config=SMALL)
    rollout = jax.jit(im.make_rollout_fn(env, PCFG), compiler_options=ENV_FAST)
    return SimpleNamespace(split=split, env=env, rollout=rollout, episodes=jnp.arange(3, dtype=jnp.int32))


def _run(hall, params, beta, seed=0):
    m, recs = hall.rollout(params, jax.random.PRNGKey(seed), hall.episodes, beta)
    return jax.tree.map(np.asarray, m), jax.tree.map(np.asarray, recs)


@pytest.fixture(scope="module")
def params0():
    return policy.init(jax.random.PRNGKey(0), PCFG)


@pytest.fixture(scope="module")
def bc(hall, params0):
    """Behaviour cloning data: the expert acting (beta = 1)."""
    return _run(hall, params0, 1.0)


@pytest.fixture(scope="module")
def trained(bc, params0, tmp_path_factory):
    """A policy run dir as `conav train policy` writes it, the policy fitted to the BC windows
    (full-batch Adam on bc_loss; train.loop's own tests cover the loop)."""
    windows = im.sequences(bc[1], SEQ, BURN_IN)
    opt = adam(3e-3)

    @functools.partial(jax.jit, compiler_options=FAST)
    def update(params, state):
        (loss, _), grads = jax.value_and_grad(im.bc_loss, has_aux=True)(params, PCFG, windows)
        params, state = opt.update(grads, state, params)
        return params, state, loss

    params, state, losses = params0, opt.init(params0), []
    for _ in range(150):
        params, state, loss = update(params, state)
        losses.append(float(loss))
    run = tmp_path_factory.mktemp("policy_run")
    config = run_config(PCFG, ImitationConfig(seq_len=SEQ, burn_in=BURN_IN), ExpertConfig(), "test", None, None)
    save_checkpoint(checkpoint_path(run, 150), params=params, opt_state=state, config=config, step=150,
                    extra={"round": 0, "val": {}, "expert_val": {}})
    return SimpleNamespace(run=run, params=params, windows=windows, losses=losses)


def test_rematerialised_bc_loss_gives_the_same_loss_and_gradients(trained, params0):
    # remat widens the compact uint8 / float16 frames one window step at a time.
    grad = jax.jit(jax.value_and_grad(im.bc_loss, has_aux=True), static_argnums=(1, 3), compiler_options=FAST)
    (plain, _), g_plain = grad(params0, PCFG, trained.windows, False)
    (remat, _), g_remat = grad(params0, PCFG, trained.windows, True)
    np.testing.assert_allclose(remat, plain, rtol=1e-5)
    for a, b in zip(jax.tree.leaves(g_remat), jax.tree.leaves(g_plain)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)


def test_bfloat16_convolutions_keep_the_bc_loss_and_its_gradients(trained):
    grad = jax.jit(jax.value_and_grad(im.bc_loss, has_aux=True), static_argnums=(1, 3), compiler_options=FAST)
    bf16 = dataclasses.replace(PCFG, conv_dtype="bfloat16")
    # The fitted policy, whose actions depend on its CNN: rounding its convolutions to bfloat16
    # moves the loss by well under 1% of itself.
    (exact, _), _ = grad(trained.params, PCFG, trained.windows, False)
    (mixed, _), _ = grad(trained.params, bf16, trained.windows, False)
    assert mixed.dtype == jnp.float32 and float(mixed) != float(exact)  # the convolutions rounded
    np.testing.assert_allclose(mixed, exact, rtol=1e-2)
    # Gradients away from the labels it was fitted to (negated): at its fitted minimum they are
    # as small as the rounding's effect on the features, so their direction would say nothing.
    away = {**trained.windows, "label": -trained.windows["label"]}
    _, g_exact = grad(trained.params, PCFG, away, False)
    flat = lambda tree: np.concatenate([np.ravel(x) for x in jax.tree.leaves(tree)])
    for remat in (False, True):
        _, g_mixed = grad(trained.params, bf16, away, remat)
        assert all(x.dtype == jnp.float32 for x in jax.tree.leaves(g_mixed))
        a, b = flat(g_exact), flat(g_mixed)
        assert np.isfinite(b).all()
        assert a @ b / (np.linalg.norm(a) * np.linalg.norm(b)) > 0.99
        c, d = flat(g_exact["convs"]), flat(g_mixed["convs"])
        assert c @ d / (np.linalg.norm(c) * np.linalg.norm(d)) > 0.99


def test_expert_in_the_simulator_reaches_the_goal_without_touching_the_human(bc):
    m, recs = bc
    assert (m["t_reach"] >= 0).all(), m["t_reach"]
    assert (m["t_reach"][:2] <= T_ARRIVE).all(), m["t_reach"]  # first to arrive
    assert (m["collided"] == 0).all() and (m["human_contact_steps"] == 0).all()  # incl. head-on
    assert summarize(m)["RASR"] == 100.0
    np.testing.assert_array_equal(recs.action, recs.label)  # beta = 1: the expert drives
    # Records stop counting at the episode's end (the step after reaching the goal).
    np.testing.assert_array_equal(recs.valid.sum(1), m["t_reach"])


def test_records_hold_compact_observations(bc):
    _, recs = bc
    assert recs.obs["rgb"].dtype == np.uint8 and recs.obs["rgb"].shape == (3, T_END + 1, 8, 32, 3)
    assert recs.obs["depth"].dtype == np.float16 and recs.obs["depth"].shape == (3, T_END + 1, 8, 32)
    assert set(recs.obs) == {"rgb", "depth", "segmentation", *im.RECORDED_KEYS}
    np.testing.assert_array_equal(recs.obs["activity_probs"].argmax(-1), 4)  # the hall's activity B


def test_rollouts_are_deterministic_for_a_seed(hall, params0):
    # A mixture draws who acts at each step from the key: same seed, same bytes.
    mixed = [_run(hall, params0, 0.5, seed=3) for _ in range(2)]
    for a, b in zip(*(jax.tree.leaves(x) for x in mixed)):
        assert a.tobytes() == b.tobytes()
    assert not np.array_equal(mixed[0][1].action, mixed[0][1].label)


def test_expert_round_data_do_not_depend_on_the_policy_so_a_run_can_record_them_again(hall, bc, trained, tmp_path):
    # train.policy records round 0 again when a resumed run lacks its file, and runs of other
    # seeds share it: the same bytes as long as neither the policy's params nor the key play a
    # part when the expert acts alone.
    for again in (_run(hall, trained.params, 1.0), _run(hall, trained.params, 1.0, seed=7)):
        for a, b in zip(jax.tree.leaves(bc), jax.tree.leaves(again)):
            assert a.tobytes() == b.tobytes()
    path = tmp_path / "data" / "round_1.npz"
    check_recordable(0, True, tmp_path / "data" / "round_0.npz", tmp_path)  # round 0: any time
    check_recordable(1, False, path, tmp_path)  # a DAgger round not yet begun
    with pytest.raises(FileNotFoundError, match="round_1.npz, the data of round 1, is missing"):
        check_recordable(1, True, path, tmp_path)


def test_records_cut_into_windows_batch_by_batch_are_the_windows_of_all_of_them(hall, params0):
    # Recording keeps only each batch's windows (the padded records of every episode at once
    # would not fit a host at paper scale): the same windows, in the same order.
    key, eps = jax.random.PRNGKey(0), np.arange(5)  # 2 batches of 3 lanes (the fixtures' compile)
    m_whole, recs = im.run_batched(hall.rollout, params0, key, eps, 1.0, batch=3)
    m_cut, windows = im.run_batched(hall.rollout, params0, key, eps, 1.0, batch=3, windows=(SEQ, BURN_IN))
    whole = im.sequences(recs, SEQ, BURN_IN)
    assert jax.tree.structure(windows) == jax.tree.structure(whole)
    # Shading's float arithmetic may round differently in differently compiled programs (chunked
    # and whole): a colour may move by one level, and the learner's actions by rounding.
    for a, b in zip(jax.tree.leaves((m_whole, whole)), jax.tree.leaves((m_cut, windows))):
        a, b = np.asarray(a), np.asarray(b)
        assert a.shape == b.shape and a.dtype == b.dtype
        np.testing.assert_allclose(a.astype(np.float64), b.astype(np.float64), rtol=1e-3, atol=1.0 if a.dtype == np.uint8 else 1e-2)


_RECORDERS = {}  # chunk length -> (recorder, jitted start, jitted advance), shared by the cases below


@pytest.mark.parametrize("beta, chunk", [(1.0, None), (0.0, 2 * SEQ), (0.5, None)])
def test_chunked_recording_keeps_the_windows_of_the_whole_rollout_and_stops_when_every_episode_ends(
        hall, params0, beta, chunk):
    # The recorder runs make_rollout_fn's steps a chunk at a time (its burn-in reaching back into
    # the chunk before) and keeps only the windows: the same windows and metrics, in the same
    # order, as cutting the whole rollout's records; the expert's episodes end at the goal, so
    # its recording stops early, the policy's run to the human's end; mixed, each step's draw
    # comes from that step's key.
    key, eps = jax.random.PRNGKey(3), np.arange(5)  # 2 batches of 3 lanes (the fixtures' compile)
    m_whole, whole = im.run_batched(hall.rollout, params0, key, eps, beta, batch=3, windows=(SEQ, BURN_IN))
    if chunk not in _RECORDERS:  # one compile per chunk length: beta is an argument
        rec = im.make_recorder(hall.env, PCFG, seq_len=SEQ, burn_in=BURN_IN, chunk_steps=chunk)
        _RECORDERS[chunk] = rec, jax.jit(rec.start), jax.jit(rec.advance, compiler_options=ENV_FAST)
    rec, start, advance = _RECORDERS[chunk]
    assert rec.chunk_steps == (chunk or SEQ) and rec.steps == hall.env.bank.max_steps
    m_cut, windows, steps_run = im.record_windows(rec, start, advance, params0, key, eps, beta, batch=3)
    assert jax.tree.structure(windows) == jax.tree.structure(whole)
    # Shading's float arithmetic may round differently in differently compiled programs (chunked
    # and whole): a colour may move by one level, and the learner's actions by rounding.
    for a, b in zip(jax.tree.leaves((m_whole, whole)), jax.tree.leaves((m_cut, windows))):
        a, b = np.asarray(a), np.asarray(b)
        assert a.shape == b.shape and a.dtype == b.dtype
        np.testing.assert_allclose(a.astype(np.float64), b.astype(np.float64), rtol=1e-3, atol=1.0 if a.dtype == np.uint8 else 1e-2)
    if beta == 1.0:  # every episode reached its goal, and ended there
        t_reach = np.asarray(m_whole["t_reach"])
        assert (t_reach >= 0).all() and t_reach.max() < steps_run < rec.steps
    elif beta == 0.0:  # the untrained policy's run to the human's end
        assert steps_run >= int(np.asarray(m_whole["t_end"]).max())


def test_recording_chunks_hold_whole_windows_and_their_burn_in():
    assert im.recorder_chunk_steps(32, 16) == 32 and im.recorder_chunk_steps(16, 40) == 48
    assert im.recorder_chunk_steps(8, 0) == 8
    env = SimpleNamespace()  # refused before the env is read
    for chunk in (24, 8):  # not a multiple of 16; shorter than the burn-in
        with pytest.raises(ValueError, match="multiple of seq_len 16 and >= burn_in 12"):
            im.make_recorder(env, PCFG, seq_len=16, burn_in=12, chunk_steps=chunk)


def test_sequences_are_windows_with_burn_in_masked_after_the_end():
    e, t = 2, 10
    valid = np.zeros((e, t), bool)
    valid[0, :7], valid[1, :3] = True, True
    steps = np.broadcast_to(np.arange(t, dtype=np.float32)[None, :, None], (e, t, 2))
    recs = im.StepRecord({"gps_compass": steps[..., :1].repeat(3, -1)}, steps, steps, valid, steps[..., :1])
    w = im.sequences(recs, seq_len=4, burn_in=2)
    # Episode 0: windows over steps [-2, 4) and [2, 8); episode 1: only [-2, 4) (the next has no valid step).
    assert w["label"].shape == (3, 6, 2) and w["obs"]["gps_compass"].shape == (3, 6, 3)
    np.testing.assert_array_equal(w["label"][1, :, 0], [2, 3, 4, 5, 6, 7])
    np.testing.assert_array_equal(w["mask"][0], [0, 0, 1, 1, 1, 1])  # burn-in out of the loss
    np.testing.assert_array_equal(w["mask"][1], [0, 0, 1, 1, 1, 0])  # step 7 is after the end
    np.testing.assert_array_equal(w["mask"][2], [0, 0, 1, 1, 1, 0])
    np.testing.assert_array_equal(w["reset"][0], [0, 0, 1, 0, 0, 0])  # the episode starts at step 0
    assert not w["reset"][1].any()


def test_label_statistics_of_hand_made_records():
    # Episode 0: 4 valid steps, the human arrives after step 1; episode 1: 2 valid steps, never arrives.
    valid = np.array([[1, 1, 1, 1, 0], [1, 1, 0, 0, 0]], bool)
    label = np.zeros((2, 5, 2), np.float32)
    label[0, :, 0] = [1.0, 0.0, 0.04, 0.5, 9.0]  # steps 1, 2 turn in place; step 4 is not recorded
    label[0, :, 1] = [0.0, 1.0, 0.5, 0.0, 0.0]  # of those, step 1 at full rate
    label[1, :, 0] = [0.5, 0.5, 0.0, 0.0, 0.0]
    action = np.zeros((2, 5, 2), np.float32)
    action[..., 0] = 1.0
    recs = im.StepRecord({}, label, action, valid, np.zeros((2, 5, 3)))
    stats = im.label_statistics(recs, {"t_arrive": np.array([1, 99])})
    assert stats["episodes"] == 2 and stats["steps_per_episode"] == 3.0
    assert stats["after_arrival_share"] == pytest.approx(2 / 6)  # steps 2, 3 of episode 0
    assert stats["turn_in_place_share"] == pytest.approx(2 / 6) and stats["full_turn_share_of_turns"] == 0.5
    assert stats["label_v_lin_mean"] == pytest.approx((1 + 0 + 0.04 + 0.5 + 0.5 + 0.5) / 6)
    assert stats["action_v_lin_mean"] == 1.0
    # |action - label| summed over (v_lin, v_ang), averaged over the valid steps.
    assert stats["action_label_l1"] == pytest.approx((0 + 2 + 1.46 + 0.5 + 0.5 + 0.5) / 6)
    with pytest.raises(ValueError, match="no recorded step"):
        im.label_statistics(recs._replace(valid=np.zeros_like(valid)), {"t_arrive": np.array([1, 99])})


def test_dagger_rounds_mix_the_expert_in_at_a_geometric_share():
    from conav_jax.train.policy import round_actor

    assert round_actor(0, ImitationConfig(dagger_beta=0.5), "expert") == ("expert", 1.0)  # behaviour cloning
    assert round_actor(1, ImitationConfig(), "expert") == ("policy", 0.0)
    assert round_actor(1, ImitationConfig(dagger_beta=0.5), "expert") == ("policy, expert at beta 0.5", 0.5)
    assert round_actor(2, ImitationConfig(dagger_beta=0.5), "expert")[1] == 0.25
    for bad in (-0.1, 1.5):
        with pytest.raises(ValueError, match="dagger_beta is a probability"):
            ImitationConfig(dagger_beta=bad)


def test_expert_label_statistics_refuses_bad_input_before_any_rollout(tiny_data, runs_32x128):
    from conav_jax.train.policy import expert_label_statistics

    runs = runs_32x128
    with pytest.raises(ValueError, match="episodes and batch must be at least 1"):
        expert_label_statistics(tiny_data, runs["policy"], episodes=0)
    with pytest.raises(ValueError, match="episodes and batch must be at least 1"):  # not "the default batch"
        expert_label_statistics(tiny_data, runs["policy"], batch=0)
    with pytest.raises(ValueError, match="intention"):  # an intention run is not a policy run
        expert_label_statistics(tiny_data, runs["intention"])
    # It trained on predicted intentions and names no predictor run: never ground truth in their place.
    with pytest.raises(ValueError, match="trained on predicted intentions"):
        expert_label_statistics(tiny_data, runs["policy"])


def test_policy_overfits_expert_actions(trained):
    assert trained.losses[-1] < 0.1 * trained.losses[0], trained.losses[::25]


@functools.partial(jax.jit, static_argnums=0, compiler_options=FAST)
def _relabel(env, poses):
    """The pure expert replayed along recorded poses (B, T, 3) of episodes 0..B-1 -> (B, T, 2)."""
    step = make_expert_step(env)

    def one(episode, poses):
        def body(carry, x):
            t, pose = x
            ud = jnp.zeros(len(UD)).at[UD["t"]].set(t)
            state = SimpleNamespace(info={"episode": episode}, pipeline_state=SimpleNamespace(qpos=pose, userdata=ud))
            action, carry = step(state, carry)
            return carry, action

        return jax.lax.scan(body, initial_carry(), (jnp.arange(poses.shape[0], dtype=jnp.float32), poses))[1]

    return jax.vmap(one)(jnp.arange(poses.shape[0]), poses)


def test_dagger_aggregates_expert_labels_of_the_policys_states(hall, bc, trained):
    m, recs = _run(hall, trained.params, 0.0, seed=1)
    valid = recs.valid
    # The policy drove (its own actions, not the expert's)...
    assert np.abs(recs.action - recs.label)[valid].max() > 1e-3
    # ...and every label is what the expert does in the state the policy reached.
    relabelled = np.asarray(_relabel(hall.env, jnp.asarray(recs.pose)))
    np.testing.assert_allclose(relabelled[valid], recs.label[valid], atol=1e-5)
    new = im.sequences(recs, SEQ, BURN_IN)
    data = im.concat_sequences([trained.windows, new])
    n_old, n_new = len(trained.windows["label"]), len(new["label"])
    assert len(data["label"]) == n_old + n_new and data["obs"]["rgb"].shape[0] == n_old + n_new
    np.testing.assert_array_equal(data["label"][n_old:], new["label"])


def _fake_intention(activity: int, obj: int, privileged: tuple = ()):
    """A stand-in intention predictor that always names `activity` and `obj` (and counts its calls)."""
    return SimpleNamespace(
        init=lambda: jnp.int32(0),
        step=lambda carry, front: (jax.nn.one_hot(activity, 107), jax.nn.one_hot(obj, 51), carry + 1),
        privileged=privileged,
    )


# "The human stays 7 m ahead", wherever they are.
FAKE_TRAJECTORY = SimpleNamespace(predict=lambda history: jnp.full(history.shape[:-2] + (PCFG.horizon, 2), 7.0))


def test_predicted_intentions_replace_ground_truth_in_the_records(hall, params0, tmp_path, tiny_data):
    rollout = jax.jit(im.make_rollout_fn(hall.env, PCFG, intention=_fake_intention(9, 11), trajectory=FAKE_TRAJECTORY,
                                         record_predicted=True, num_steps=24), compiler_options=ENV_FAST)
    for beta in (1.0, 0.0):  # the predictors follow the expert's steps and the policy's alike
        _, recs = jax.tree.map(np.asarray, rollout(params0, jax.random.PRNGKey(0), hall.episodes, beta))
        np.testing.assert_array_equal(recs.obs["future_traj"], 7.0)
        np.testing.assert_array_equal(recs.obs["activity_probs"].argmax(-1), 9)  # the truth is 4
        np.testing.assert_array_equal(recs.obs["object_probs"].argmax(-1), 11)
    with pytest.raises(ValueError, match="needs the predictor of every intention input"):
        im.make_rollout_fn(hall.env, PCFG, record_predicted=True)
    # A policy never reads predictions for one input and ground truth for another.
    with pytest.raises(ValueError, match=r"no intention predictor is given \(intention_run\)"):
        im.make_rollout_fn(hall.env, PCFG, trajectory=FAKE_TRAJECTORY, record_predicted=True)
    # Training on predicted intentions names the missing predictor runs up front.
    with pytest.raises(ValueError, match="predictor runs intention_run, trajectory_run"):
        train_policy_from_data(tiny_data, tmp_path / "run", TrainConfig(steps=1, warmup_steps=0), PCFG,
                               ImitationConfig(train_intentions="predicted"))
    assert not (tmp_path / "run").exists()
    with pytest.raises(ValueError, match="unknown train_intentions"):
        ImitationConfig(train_intentions="oracle")
    # Table 3's first row reads no intention input: it records without predictors, whatever is given.
    predicted, fake = ImitationConfig(train_intentions="predicted"), _fake_intention(9, 11)
    assert records_predictions(predicted, PCFG, fake, FAKE_TRAJECTORY)
    assert not records_predictions(predicted, policy.ablation_config(PCFG, "none"), fake, FAKE_TRAJECTORY)
    assert not records_predictions(ImitationConfig(), PCFG, fake, FAKE_TRAJECTORY)


def test_a_predictor_reading_the_segmentation_adds_it_to_the_agents_privileged_inputs():
    from conav_jax.envs.agents.policy import privileged_inputs

    seg = ("oracle segmentation",)
    reads_seg = _fake_intention(9, 11, privileged=seg)
    activity_only = policy.ablation_config(PCFG, "activity")
    assert not activity_only.uses_saliency
    assert privileged_inputs(activity_only, "predicted", _fake_intention(9, 11)) == ()
    assert privileged_inputs(activity_only, "predicted", reads_seg) == seg
    assert privileged_inputs(PCFG, "predicted", reads_seg) == seg  # listed once
    # A policy that reads no intention input never runs the predictor.
    assert privileged_inputs(policy.ablation_config(PCFG, "none"), "none", reads_seg) == ()


def test_policy_agent_runs_in_evaluate_with_ground_truth_only_when_asked(hall, trained):
    agent = policy_agent(hall.env, trained.run, ground_truth=True)
    assert agent.name == "conav" and agent.intention_source == "ground_truth"
    assert agent.privileged == ("ground-truth intentions", "future human positions", "oracle segmentation")
    m = evaluate(hall.env, agent, np.asarray(hall.episodes), batch=3, compiler_options=ENV_FAST)
    assert {"FASR", "RASR", "FASPL", "RASPL", "CR", "AS"} <= set(summarize(m))
    assert (m["nan_actions"] == 0).all()
    # The same policy through imitation's own rollout (how training validates) acts alike.
    ours, _ = _run(hall, trained.params, 0.0, seed=1)
    np.testing.assert_allclose(m["path_length_m"], ours["path_length_m"], atol=0.05)


def test_the_conav_agent_refuses_to_run_without_predictors(hall, trained):
    # The run names no predictor runs and none are given: no silent ground truth.
    with pytest.raises(ValueError, match="pass intention_run \\(or ground_truth=True"):
        policy_agent(hall.env, trained.run)


def test_at_evaluation_the_policy_reads_the_predictors_outputs_not_the_truth(hall, trained, tmp_path, monkeypatch):
    from conav_jax.envs.agents import policy as agent_policy

    runs = [tmp_path / "intention", tmp_path / "trajectory"]
    for r in runs:
        r.mkdir()
    fakes = (_fake_intention(9, 11), FAKE_TRAJECTORY)
    monkeypatch.setattr(agent_policy, "load_predictors", lambda i, t: fakes if (i, t) == tuple(map(str, runs)) else None)
    agent = policy_agent(hall.env, trained.run, intention_run=runs[0], trajectory_run=runs[1])
    assert agent.intention_source == "predicted" and agent.privileged == ("oracle segmentation",)
    state = jax.jit(hall.env.reset_to_episode, compiler_options=ENV_FAST)(jax.random.PRNGKey(0), 0)
    pol, truth_pol = make_policy_step(PCFG, *fakes), make_policy_step(PCFG)

    @functools.partial(jax.jit, compiler_options=ENV_FAST)
    def act(state):
        obs = {k: state.obs[k] for k in agent.reads}
        carry, action = agent.act(agent.init(jax.random.PRNGKey(0), obs), obs, jax.random.PRNGKey(1))
        inputs, _ = pol.predict(state.obs, pol.init())
        expected, _ = pol.act(trained.params, inputs, pol.init())
        truth, _ = truth_pol.step(trained.params, state.obs, truth_pol.init())
        return action, carry, expected, truth

    action, carry, expected, truth = act(state)
    assert int(carry.predicted["activity_probs"].argmax()) == 9 != int(state.obs["activity_probs"].argmax())
    assert int(carry.predicted["object_probs"].argmax()) == 11 != int(state.obs["object_probs"].argmax())
    np.testing.assert_array_equal(carry.predicted["future_traj"], 7.0)
    # The action is the policy's on the predictions, and not what the truth would give.
    np.testing.assert_allclose(action, expected, atol=1e-6)
    assert not np.allclose(action, truth, atol=1e-4)


def test_policy_agent_rejects_wrong_runs_before_compiling(hall, trained, tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        policy_agent(hall.env, tmp_path / "missing")
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        policy_agent(hall.env, tmp_path)
    other = tmp_path / "trajectory_run"
    save_checkpoint(checkpoint_path(other, 1), params={"w": np.zeros(2)}, opt_state=None,
                    config={"kind": "trajectory", "model": {}}, step=1)
    with pytest.raises(ValueError, match="'trajectory' run"):
        policy_agent(hall.env, other)
    wide = ConavEnv(episodes=hall.split, config=EnvConfig(sensor=SensorConfig(resolution=(16, 64))))
    with pytest.raises(ValueError, match="8x32 panoramas but the env renders 16x64"):
        policy_agent(wide, trained.run, ground_truth=True)
    # The ground truth is read only by declaring it, whatever the env's brax observation holds.
    blind = ConavEnv(episodes=hall.split, config=EnvConfig(sensor=SMALL.sensor, intention_obs=False))
    truth = policy_agent(blind, trained.run, ground_truth=True)
    assert {"activity_probs", "object_probs", "future_traj"} <= set(truth.reads)
    assert truth.privileged[:2] == ("ground-truth intentions", "future human positions")


def test_predictor_runs_default_to_the_ones_the_policy_run_names(tmp_path):
    intention, trajectory = tmp_path / "intention", tmp_path / "trajectory"
    intention.mkdir()
    trajectory.mkdir()
    named = {"intention_run": str(intention), "trajectory_run": str(trajectory)}
    assert predictor_runs(PCFG, "run", named) == (str(intention), str(trajectory))
    assert predictor_runs(PCFG, "run", named, str(trajectory)) == (str(trajectory), str(trajectory))
    assert predictor_runs(PCFG, "run", named, ground_truth=True) == (None, None)  # ground truth asked for
    # An ablation that reads no trajectory needs no trajectory run, named or not.
    no_traj = dataclasses.replace(PCFG, use_trajectory=False)
    assert predictor_runs(no_traj, "run", {"intention_run": str(intention)}) == (str(intention), None)
    with pytest.raises(ValueError, match="excludes intention_run / trajectory_run"):
        predictor_runs(PCFG, "run", named, str(intention), None, True)
    with pytest.raises(ValueError, match="reads trajectory predictions and no trajectory predictor run is given"):
        predictor_runs(PCFG, "run", {"intention_run": str(intention)})
    with pytest.raises(ValueError, match="named by run"):
        predictor_runs(PCFG, "run", {"intention_run": str(tmp_path / "gone"), "trajectory_run": str(trajectory)})
    with pytest.raises(ValueError, match=r"\(given\) not found"):
        predictor_runs(PCFG, "run", named, str(tmp_path / "gone"))
