"""The intention predictor on flat category colours and on instance materials: the same data,
schedule and seeds, minival top-1 in each run's log.jsonl.

usage: python intention_materials.py DATA MATERIALS SEED OUT   (DATA: `conav generate --preset small`)
"""
import sys

from conav_jax.models.perceiver import PerceiverConfig
from conav_jax.train import intention
from conav_jax.train.loop import TrainConfig

data, materials, seed, out = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
schedule = TrainConfig(steps=6000, batch=64, lr=3e-4, weight_decay=0.01, seed=seed, val_every=3000,
                       ckpt_every=6000, log_every=50)  # the predictor's own schedule, validated twice
intention.train_intention_from_data(data, out, schedule, PerceiverConfig(image_hw=(32, 32)),
                                    intention.IntentionDataConfig(resolution=(32, 128), materials=materials),
                                    progress=False)
