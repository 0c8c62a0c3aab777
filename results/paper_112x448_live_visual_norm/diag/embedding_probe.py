"""Does the 112x448 visual layer die at lr 1e-3 in the live trainer? Loop K iterations by hand."""
import sys, time, json
import jax, jax.numpy as jnp, numpy as np
from conav_jax.models import policy
from conav_jax.models.policy import PolicyConfig, encoder_config, ablation_config
from conav_jax.train.live import LiveConfig, make_iteration, iteration_key
from conav_jax.envs import EnvConfig, SensorConfig
from conav_jax.envs.conav_env import ConavEnv
lr, hw, lanes, K = float(sys.argv[1]), tuple(map(int, sys.argv[2].split("x"))), int(sys.argv[3]), int(sys.argv[4])
data = sys.argv[5] if len(sys.argv) > 5 else "/tmp/demo-out/data"
cfg = ablation_config(encoder_config(PolicyConfig(image_hw=hw, conv_dtype="bfloat16", visual_norm=len(sys.argv) > 6 and sys.argv[6] == "norm"), "patch"), "all")
live = LiveConfig(lanes=lanes, window_steps=16, iterations=1000, lr=lr, warmup_iterations=50, remat=True)
env = ConavEnv(data, "train", EnvConfig(sensor=SensorConfig(resolution=hw), end_at_reach=True))
fns, it_fn = make_iteration(env, cfg, live)
state = fns.init(policy.init(jax.random.PRNGKey(0), cfg))
# probe observations: first steps of 16 train episodes
probe = jax.vmap(lambda e: env.reset_to_episode(jax.random.PRNGKey(0), e).obs)(jnp.arange(16))
probe = {k: probe[k] for k in policy.policy_inputs(cfg) if k in probe} if hasattr(policy, "policy_inputs") else probe
def diag(params):
    import conav_jax.nn as nn
    x = policy.encode(params, cfg, probe)
    vis = x[:, :cfg.visual_dim]
    alive = float((vis > 0).any(0).mean())
    carry = policy.initial_carry(cfg, 16)
    out = policy.apply(params, cfg, probe, carry)
    a = out[0]
    return {"visual_alive": round(alive, 3), "visual_mean": round(float(vis.mean()), 3), "feat_absmax": round(float(jnp.abs(x).max()), 2),
            "action_std": [round(float(s), 4) for s in a.std(0)]}
print("init", diag(state.params), flush=True)
t = time.time()
for i in range(K):
    state, m = it_fn(state, iteration_key(0, i))
    if (i + 1) % 5 == 0:
        print(i + 1, round(float(m["loss"]), 4), round(float(m["grad_norm"]), 3), f"{float(m['lr']):.2e}", diag(state.params), round(time.time() - t), "s", flush=True)
