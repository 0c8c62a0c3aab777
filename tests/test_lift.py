"""envs.agents.lift in the hand-built hall: an agent's floating-point arrays become arguments and
the agent acts as before with them; the key is one for agents of one program whatever their
weights, and holds by value what a batching rule closes over. Nothing here compiles a rollout."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from worlds import make_split

from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
from conav_jax.envs.agents.base import Agent
from conav_jax.envs.agents.lift import lift_agent

KEY = jax.random.PRNGKey(0)
W = jax.random.normal(KEY, (2, 4))
OBS = {"gps_compass": jnp.array([1.0, 2.0, 0.5])}


@pytest.fixture(scope="module")
def hall():
    return ConavEnv(episodes=make_split([(2.5, 2.0, 0.0)]), config=EnvConfig(sensor=SensorConfig(resolution=(8, 32))))


def _linear(w):
    """An agent steering by an affine map of its GPS/compass, `w` (2, 4) closed over; it counts its steps."""
    return Agent("linear", lambda key, obs: jnp.int32(0),
                 lambda carry, obs, key: (carry + 1, jnp.tanh(w[:, :3] @ obs["gps_compass"] + w[:, 3])),
                 reads=("gps_compass",))


def _ruled(w):
    """An agent whose batching rule (jax.custom_batching) closes over `w` (2, 3)."""

    @jax.custom_batching.custom_vmap
    def steer(x):
        return w @ x

    @steer.def_vmap
    def rule(axis_size, in_batched, x):
        return x @ w.T, True

    return Agent("ruled", lambda key, obs: (), lambda carry, obs, key: (carry, jnp.tanh(steer(obs["gps_compass"]))),
                 reads=("gps_compass",))


def test_weights_become_arguments_and_the_agent_acts_as_before(hall):
    lifted = lift_agent(hall, _linear(W))
    assert [p.shape for p in jax.tree.leaves(lifted.params)] == [(2, 4)]
    other = lift_agent(hall, _linear(2 * W))
    assert other.key == lifted.key  # other weights, one program
    for w, params in ((W, lifted.params), (2 * W, other.params)):
        agent = lifted.agent_fn(params)  # the first agent's functions with the weights given
        carry = agent.init(KEY, OBS)
        for got, want in zip(agent.act(carry, OBS, KEY), _linear(w).act(carry, OBS, KEY)):
            np.testing.assert_array_equal(got, want)
    assert lift_agent(hall, _linear(jnp.ones((2, 5)))).key != lifted.key  # other shapes, another program
    with pytest.raises(ValueError, match="traced for arguments"):
        lifted.agent_fn(lifted.params).act(jnp.int32(0), {"gps_compass": jnp.zeros(4)}, KEY)


def test_what_a_batching_rule_closes_over_stays_in_the_key(hall):
    w = W[:, :3]
    assert lift_agent(hall, _ruled(w)).key != lift_agent(hall, _ruled(2 * w)).key
    assert lift_agent(hall, _ruled(w)).key == lift_agent(hall, _ruled(w + 0.0)).key  # equal values, equal keys


def test_agents_calling_back_to_the_host_share_no_program(hall):
    def calling(scale):  # the function called back is in no program text
        def act(carry, obs, key):
            action = jax.pure_callback(lambda x: np.asarray(x) * np.float32(scale),
                                       jax.ShapeDtypeStruct((2,), jnp.float32), obs["gps_compass"][:2],
                                       vmap_method="sequential")
            return carry, action

        return Agent("calling", lambda key, obs: (), act, reads=("gps_compass",))

    assert lift_agent(hall, calling(0.5)).key != lift_agent(hall, calling(0.25)).key
