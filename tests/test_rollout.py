"""envs.rollout's evaluator: lanes refilled as episodes end give, episode by episode, the final
metrics of full-length fixed-batch rollouts, for a stochastic agent (keys per episode) whose
episodes end at different steps; bad episode lists are rejected."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from worlds import make_split

from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
from conav_jax.envs.agents.registry import make_agent
from conav_jax.envs.agents.base import StateAgent
from conav_jax.envs.rollout import evaluate, make_evaluator

T_ARRIVE, T_END = 140, 160  # the human walks from the fridge to the table in steps 70-140
# Compile time dominates on a CPU: without LLVM optimisation and XLA's fusion emitters the
# rollouts compile several times faster (same results, slower to run).
FAST = {"xla_backend_optimization_level": 0, "xla_cpu_use_fusion_emitters": False}


@pytest.fixture(scope="module")
def env():
    starts = [(2.5, 2.0, 0.0), (7.5, 3.0, np.pi), (5.0, 1.0, 1.0), (3.0, 3.0, -1.0), (8.0, 1.5, 2.0), (6.0, 2.5, 0.5)]
    # Episodes end at the first reach here, so they end at different steps and lanes refill.
    config = EnvConfig(sensor=SensorConfig(resolution=(8, 32)), end_at_reach=True)
    return ConavEnv(episodes=make_split(starts, t_arrive=T_ARRIVE, t_end=T_END), config=config)


@pytest.fixture(scope="module")
def noisy_expert(env):
    """The expert with key-drawn noise on its actions: it reaches the goal at different steps
    in different episodes, and its actions depend on the keys."""
    expert = make_agent("expert", env)

    def act(state, carry, key):
        action, carry = expert.act(state, carry, key)
        return jnp.clip(action + 0.3 * jax.random.normal(key, (2,)), -1.0, 1.0), carry

    return StateAgent("noisy_expert", expert.init, act)


def test_refilled_lanes_match_full_length_batches(env, noisy_expert):
    episodes = np.array([4, 0, 5, 2, 1, 3])
    evaluator = make_evaluator(env, lambda _: noisy_expert, batch=2, seed=7, trace_first=True,
                               compiler_options=FAST)  # 2 lanes, 6 episodes
    pooled, first, first_trace = evaluator(None, episodes)
    # The reference: lanes for every episode, one full-length batch (make_param_rollout, what
    # fixed-batch sweeps ran), no refills.
    reference, first_b, trace_b = make_evaluator(env, lambda _: noisy_expert, batch=8, seed=7, trace_first=True,
                                                 compiler_options=FAST)(None, episodes)
    reached = reference["t_reach"]
    assert len(set(reached.tolist())) > 2 and 0 <= reached.min() < T_END - 16  # early, different ends: lanes refill
    # With end_at_reach an episode stops at its first reach, and reports no CR_full.
    np.testing.assert_array_equal(reference["t"][reached >= 0], reached[reached >= 0])
    assert "collided_full" not in reference
    np.testing.assert_array_equal(pooled["episode"], episodes)
    for k, v in reference.items():
        np.testing.assert_array_equal(pooled[k], v, err_msg=k)
    # The traced episode is the longest (the lanes take it first), recorded up to its end.
    j = int(np.argmax(np.asarray(env.bank.t_end)[episodes]))
    assert first == first_b == episodes[j] and first_trace.done[-1] > 0 and (first_trace.done[:-1] == 0).all()
    for name, a, b in zip(first_trace._fields, first_trace, trace_b):
        np.testing.assert_array_equal(a, b, err_msg=name)
    # Reversed, each episode runs in another lane at another time: the same bytes (an episode's
    # keys do not depend on its lane; the same compiled rollout serves).
    again, _, _ = evaluator(None, episodes[::-1])
    for k in reference:
        assert pooled[k].tobytes() == again[k][::-1].tobytes(), k


def test_evaluate_rejects_bad_episode_lists(env, noisy_expert):
    for bad in (np.array([], int), np.array([[0, 1]]), np.array([0, 6]), np.array([-1])):
        with pytest.raises(ValueError, match="episode"):
            evaluate(env, noisy_expert, bad)


def test_trace_step_reads_the_contacts_of_one_env_and_of_a_batch():
    from types import SimpleNamespace

    from conav_jax.envs.mjcf import UD
    from conav_jax.envs.rollout import trace_step

    ud = np.zeros((3, len(UD)), np.float32)
    ud[1, UD["human_touch"]], ud[2, UD["wall_touch"]] = 1.0, 1.0

    def state(k):
        ps = SimpleNamespace(userdata=ud[k], qpos=np.zeros(ud[k].shape[:-1] + (3,)))
        return SimpleNamespace(pipeline_state=ps, reward=np.zeros(ud[k].shape[:-1]), done=np.zeros(ud[k].shape[:-1]))

    batch = trace_step(state(slice(None)), np.zeros((3, 2)))
    np.testing.assert_array_equal(batch.human_contact, [0, 1, 0])
    np.testing.assert_array_equal(batch.wall_contact, [0, 0, 1])
    one = trace_step(state(2), np.zeros(2))
    assert float(one.human_contact) == 0.0 and float(one.wall_contact) == 1.0


def test_compiled_rollouts_take_the_episode_bank_as_an_argument_not_as_constants(env, noisy_expert):
    import re

    from conav_jax.envs.rollout import make_param_rollout

    run = make_param_rollout(env, lambda _: noisy_expert, 4)
    text = run.lower(None, jax.random.PRNGKey(0), jnp.arange(2, dtype=jnp.int32)).as_text()
    b = env.bank
    n, t = b.joints_local.shape[:2]
    assert f"tensor<{n}x{t}x22x3xf16>" in text  # the humanoid's joints: an argument
    # No constant of the program holds episode data (the largest bank arrays are tens of kB here).
    biggest = max((len(c) for c in re.findall(r'dense<"0x[0-9A-F]*">', text)), default=0)
    assert biggest < 4 * int(b.fields[0, 0].size), biggest


def test_sweeps_render_no_image_for_an_agent_that_reads_none(env, noisy_expert):
    """The expert reads no observation key: its sweep neither traces nor computes a panorama
    (each step observes only the keys the agent reads)."""
    from conav_jax.envs.rollout import make_pool_rollout

    h, w = env.config.sensor.height, env.config.sensor.width
    run = make_pool_rollout(env, lambda _: noisy_expert, slots=2, compiler_options=FAST)
    lowered = run.lower(None, jax.random.PRNGKey(0), jnp.arange(3, dtype=jnp.int32), jnp.int32(3))
    assert f"x{h}x{w}x4xf32>" not in lowered.as_text()  # the render is not even traced ...
    compiled = lowered.compile().as_text()
    assert f",{h},{w}]" not in compiled and f",{h},{w},4]" not in compiled  # ... so no image is computed


def test_the_pool_program_is_the_refilling_rollout_the_evaluator_runs(env, noisy_expert):
    """`pool_program` hands out the evaluator's own refilling rollout (its compile cache), with
    the queue longest first, and refuses episodes that fit in the lanes (no refilling then).
    With `max_chunks` it is the same program stopped early: a profile's short trace."""
    evaluator = make_evaluator(env, lambda _: noisy_expert, batch=2, compiler_options=FAST)
    with pytest.raises(ValueError, match="fit in 2 lanes"):
        evaluator.pool_program(None, np.array([0, 1]))
    with pytest.raises(ValueError, match="max_chunks must be at least 1"):
        evaluator.pool_program(None, np.array([0, 1, 2]), max_chunks=0)
    run, args = evaluator.pool_program(None, np.array([0, 1, 2]))
    again, _ = evaluator.pool_program(None, np.array([2, 0, 1]))
    assert again is run
    t_end = np.asarray(env.bank.t_end)
    assert list(t_end[np.asarray(args[2])]) == sorted(t_end[[0, 1, 2]], reverse=True) and int(args[3]) == 3
    short, one_chunk = evaluator.pool_program(None, np.array([0, 1, 2]), max_chunks=1)
    assert short is run and int(one_chunk[4]) == 1
    whole, early = run(*args), run(*one_chunk)
    # Every episode ran to its end in the sweep; after one chunk the third, still queued, never started.
    assert (np.asarray(whole["t"]) > 0).all() and np.asarray(early["t"])[2] == 0


def test_evaluators_compile_their_rollouts_with_the_given_options(env, noisy_expert, monkeypatch):
    """Both rollouts (one full-length batch, refilled lanes) of make_evaluator and evaluate go to
    jax.jit with the options, and jax.jit is given them (an unknown one is refused when the
    program compiles)."""
    from conav_jax.envs import rollout

    options = {"xla_no_such_option": False}
    with pytest.raises(Exception, match="No such compile option: 'xla_no_such_option'"):
        rollout.jit_with_bank(env, lambda x: x + 1, compiler_options=options)(jnp.float32(1.0))
    given = []

    class NotCompiled(Exception):
        pass

    def jit_with_bank(env, fn, mesh=None, **jit_kwargs):  # records what each rollout is jitted with, compiles nothing
        given.append(jit_kwargs)

        def run(*args):
            raise NotCompiled

        return run

    monkeypatch.setattr(rollout, "jit_with_bank", jit_with_bank)
    evaluator = make_evaluator(env, lambda _: noisy_expert, batch=2, compiler_options=options)
    for episodes in (np.array([0, 1]), np.array([0, 1, 2])):  # a lane each; refilled lanes
        with pytest.raises(NotCompiled):
            evaluator(None, episodes)
        with pytest.raises(NotCompiled):
            evaluate(env, noisy_expert, episodes, batch=2, compiler_options=options)
    assert given == [{"compiler_options": options}] * 4
