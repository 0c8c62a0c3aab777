"""The learned object-goal agent (given the goal category) on flat category colours and on
instance materials: trained live on the same data, budget and seed, with or without the
saliency channel (oracle segmentation), then evaluated on minival.

usage: python objectgoal_materials.py DATA MATERIALS SALIENCY SEED ITERATIONS OUT
  DATA: `conav generate --preset small`; MATERIALS: flat | instance; SALIENCY: saliency | nosaliency
Prints one JSON line: the run's settings, its training and evaluation seconds and the minival summary.
"""
import json
import sys
import time

import conav_jax
from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
from conav_jax.envs.agents.registry import make_agent
from conav_jax.train.goalnav import objectnav_model, train_objectnav_live
from conav_jax.train.live import LiveConfig

data, materials, saliency, seed, iterations, out = sys.argv[1:7]
resolution = (32, 128)
sensor = SensorConfig(resolution=resolution, materials=materials)
env = ConavEnv(data, "train", EnvConfig(sensor=sensor, end_at_reach=True))
model = objectnav_model(resolution, object_saliency=saliency == "saliency")
live = LiveConfig(lanes=64, window_steps=16, iterations=int(iterations), lr=1e-3, warmup_iterations=10,
                  seed=int(seed), log_every=10, ckpt_every=int(iterations))
start = time.time()
run = train_objectnav_live(env, model, live, out, progress=False)
train_s = time.time() - start
minival = ConavEnv(data, "minival", EnvConfig(sensor=sensor))
start = time.time()
results = conav_jax.evaluate(minival, make_agent("objectgoal-oracle", minival, checkpoint=out), seed=0)
print(json.dumps({"materials": materials, "saliency": saliency, "seed": int(seed), "iterations": int(iterations),
                  "env_steps": run.env_steps, "train_s": round(train_s, 1), "eval_s": round(time.time() - start, 1),
                  "minival": results.summary}, default=float))
