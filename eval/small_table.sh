#!/usr/bin/env bash
# Reproduce the README's `small`-preset agent table on one GPU (the device tool's H100).
#
#   bash eval/small_table.sh OUT [imitation|rl|eval|all]
#
# imitation: data, intention + trajectory predictors, BC (all inputs / no intention inputs),
#            DAgger (the BC run continued with 2 rounds)
# rl:        PPO from scratch and PPO fine-tuned from the DAgger policy (needs imitation)
# eval:      every agent on the 500 val episodes -> OUT/eval*/report.md (needs both)
# Every stage resumes or skips what OUT already holds, so the stages may run in separate calls.
# Policies read 32x128 panoramas (not the paper's 112x448): the imitation data of 112x448
# panoramas for 1,000 episodes would not fit in host memory, and PPO's rollout buffer grows
# with the pixel count.
set -euo pipefail
OUT=${1:?usage: small_table.sh OUT [imitation|rl|eval|all]}
STAGE=${2:-all}
RES=${RES:-32x128}
SEED=${SEED:-0}
DATA=$OUT/data
conav() { python3 -m eval.cli "$@"; }
stamp() { echo "[$(date +%T)] $*"; }

[ -f "$DATA/manifest.json" ] || conav generate --preset small --out "$DATA" --seed "$SEED" --workers "$(nproc)"

if [[ $STAGE == imitation || $STAGE == all ]]; then
  stamp intention
  conav train intention --data "$DATA" --out "$OUT/intention" --steps 2000 --batch 256 --lr 1e-3 \
    --weight-decay 0.05 --val-every 1000 --ckpt-every 1000 --log-every 100 --seed "$SEED" --no-progress
  stamp trajectory
  conav train trajectory --data "$DATA" --out "$OUT/trajectory" --steps 3000 --batch 1024 --lr 1e-3 \
    --val-every 1000 --ckpt-every 1000 --log-every 100 --seed "$SEED" --no-progress
  # Same flags for every policy run, so the DAgger run resumes the BC-all run's checkpoint.
  POLICY=(--data "$DATA" --intention "$OUT/intention" --trajectory "$OUT/trajectory" --resolution "$RES"
          --episodes 1000 --val-episodes 128 --steps 2000 --dagger-steps 1000 --batch 256 --lr 5e-4
          --rollout-batch 500 --log-every 100 --val-every 1000 --ckpt-every 1000 --seed "$SEED" --no-progress)
  for ab in all none; do
    stamp "bc $ab"
    conav train policy "${POLICY[@]}" --ablation $ab --out "$OUT/bc_$ab"
  done
  stamp dagger
  [ -d "$OUT/dagger" ] || { mkdir -p "$OUT/dagger"; cp "$OUT/bc_all"/ckpt_* "$OUT/bc_all/log.jsonl" "$OUT/dagger/";
                           mkdir -p "$OUT/dagger/data"; cp "$OUT/bc_all/data/round_0.npz" "$OUT/dagger/data/"; }
  conav train policy "${POLICY[@]}" --ablation all --out "$OUT/dagger" --dagger-rounds 2
fi

if [[ $STAGE == rl || $STAGE == all ]]; then
  RL=(--data "$DATA" --resolution "$RES" --num-envs 512 --rollout-steps 64 --eval-every 20 --ckpt-every 20 --seed "$SEED"
      --no-progress)
  stamp "ppo scratch"
  [ -d "$OUT/ppo_scratch" ] || conav train rl "${RL[@]}" --feedforward --steps 15000000 --out "$OUT/ppo_scratch"
  stamp "ppo finetune"
  [ -d "$OUT/ppo_finetune" ] || conav train rl "${RL[@]}" --init-from "$OUT/dagger" --steps 5000000 --lr 3e-5 \
    --out "$OUT/ppo_finetune"
fi

if [[ $STAGE == eval || $STAGE == all ]]; then
  stamp eval
  conav eval --data "$DATA" --split val --resolution "$RES" --batch 500 --seed "$SEED" \
    --agent random,follower,pioneer,objectgoal,expert,conav --checkpoint "$OUT/dagger" \
    --ablation-checkpoints "none=$OUT/bc_none,all=$OUT/bc_all" --out "$OUT/eval"
  for run in ppo_scratch ppo_finetune; do
    [ -d "$OUT/$run" ] && conav eval --data "$DATA" --split val --resolution "$RES" --batch 500 --seed "$SEED" \
      --agent ppo --checkpoint "$OUT/$run" --out "$OUT/eval_$run"
  done
fi
stamp done
