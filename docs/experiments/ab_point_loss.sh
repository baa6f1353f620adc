#!/usr/bin/env bash
# A/B: the paper's loss against the paper's loss + the virtual-point loss, 150 steps each from the shipped default.
cd "$(dirname "$0")/../.." && mkdir -p runs
for w in 0 1; do
  .venv/bin/o3dsoft train --protocol incongruent-mix --init default --lr 3e-4 --batch-size 10 --seed 11 \
    --data ../shared/data/modelnet40_ply_hdf5_1024 --max-steps 150 --eval-pairs 100 --epochs 1 \
    --point-loss $w --out runs/ab_point$w > runs/ab_point$w.log 2>&1
done
for w in 0 1; do
  .venv/bin/python -m benchmarks.eval_model --weights runs/ab_point$w/model.pt --protocol dcp incongruent --limit 100 --search off \
    --data ../shared/data/modelnet40_ply_hdf5_1024 > runs/ab_point$w.eval.json 2>&1
done
echo done > runs/ab_point.done
