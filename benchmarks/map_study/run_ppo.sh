#!/bin/bash
# PPO RL-sparse and RL-rich, SSSG, seeds 0-2, default 40k budget and PPO settings.
cd "$(dirname "$0")/../.."
for name in "$@"; do
  .venv/bin/bgrl reproduce --out results/map_study/$name --tasks sssg --methods rl_sparse,rl_rich \
    --seeds 3 --workers 2 --map services/sim/maps/$name.json
done
