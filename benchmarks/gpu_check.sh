#!/usr/bin/env bash
# The GPU checks of one short lease, in one script (benchmarks/README.md, "On a GPU"):
#   1. the GPU-only tests and the layers' tests (test_engine, test_wide, test_conv),
#   2. one layer in every form (benchmarks/conv.py) and the U-Net's training step,
#   3. the 15-minute segmentation recipe (make demo-seg) trained and scored on CUDA, timed.
# Run from the repository root with python3 holding a CUDA PyTorch:
#   WHEELS=dir  wheels installed first into /tmp/site (what the machine lacks:
#               torch-scatter, torch-cluster, trimesh, embreex, pycocotools)
#   OUT=dir     the log and the recipe's results.json (default runs/gpu_check)
set -u
OUT=${OUT:-runs/gpu_check}
mkdir -p "$OUT"
exec > >(tee -a "$OUT/gpu.log") 2>&1
export PYTHONUNBUFFERED=1
t0=$(date +%s)
lap() { echo "== $(( $(date +%s) - t0 )) s: $*"; }
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
if [ -n "${WHEELS:-}" ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site "$WHEELS"/*.whl || exit 1
  export PYTHONPATH=/tmp/site
fi
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
python3 -c "import torch, torch_geometric, torch_scatter, torch_cluster, trimesh, embreex; \
print('torch', torch.__version__, 'pyg', torch_geometric.__version__, 'cuda', torch.cuda.is_available())" \
  || exit 1
lap "set up"
timeout 150 python3 -m pytest -q -p no:cacheprovider -rs tests/train/test_engine.py tests/nn/test_wide.py \
  tests/nn/test_conv.py
lap "tests"
timeout 90 python3 benchmarks/conv.py --device cuda --level 6 --reps 10 --skip-slow
timeout 45 python3 benchmarks/seg_step.py --device cuda --batch 32 --reps 5
lap "layer and step"
timeout 290 python3 -m usf_graph.cli train seg --device cuda --channel-scale 0.5 --epochs 6 \
  --fov-epochs 2 --up-epochs 4 --up-extra 400 --root /tmp/rooms --out /tmp/seg_gpu
cp /tmp/seg_gpu/results.json "$OUT/seg_results.json" 2>/dev/null
lap "segmentation recipe"
