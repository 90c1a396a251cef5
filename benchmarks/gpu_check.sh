#!/usr/bin/env bash
# The GPU checks of one short lease, in one script (benchmarks/README.md, "On a GPU"):
#   1. the GPU-only tests and the layers' tests (test_engine, test_wide, test_conv,
#      test_torch_modes: autocast, inference mode, compile; test_gravity: the up's polish),
#   2. one layer in every form (benchmarks/conv.py), the U-Net's training step and one frame of
#      predict (benchmarks/predict_frame.py),
#   3. a 15-minute recipe trained and scored on CUDA, timed (RECIPE=seg: make demo-seg, the
#      default; RECIPE=det: make demo-det; RECIPE=both: the two side by side; RECIPE=none).
# Run from the repository root with python3 holding a CUDA PyTorch:
#   WHEELS=dir  wheels installed first into /tmp/site (what the machine lacks:
#               torch-scatter, torch-cluster, trimesh, embreex, pycocotools, healpy with
#               astropy, astropy-iers-data, pyerfa). The two compiled ones, for the machine's
#               Python 3.12 and torch 2.11.0: in a Python 3.12 venv holding PyPI's
#               torch==2.11.0 with its nvidia packages (import torch needs them), run
#               FORCE_ONLY_CPU=1 pip wheel --no-build-isolation --no-deps
#               torch-scatter==2.1.2 torch-cluster==1.6.3 (23 min on 2 cores, session 66);
#               the rest: pip download --only-binary=:all: --python-version 3.12 ...
#   OUT=dir     the log and the recipe's results.json (default runs/gpu_check)
#   TESTS=-k..  pytest's selection within the five files (default: all of them)
#   BENCH=0     skip step 2
set -u
OUT=${OUT:-runs/gpu_check}
RECIPE=${RECIPE:-seg}
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
timeout 210 python3 -m pytest -q -p no:cacheprovider -rs tests/train/test_engine.py tests/nn/test_wide.py \
  tests/nn/test_conv.py tests/models/test_torch_modes.py tests/models/test_gravity.py ${TESTS:-}
lap "tests"
if [ "${BENCH:-1}" != 0 ]; then
  timeout 90 python3 benchmarks/conv.py --device cuda --level 6 --reps 10 --skip-slow
  timeout 45 python3 benchmarks/seg_step.py --device cuda --batch 32 --reps 5
  timeout 45 python3 benchmarks/det_step.py --device cuda --batch 32 --reps 5
  timeout 60 python3 benchmarks/predict_frame.py --device cuda --reps 5
  lap "layer and step"
fi
seg_recipe() { timeout 400 python3 -m usf_graph.cli train seg --device cuda --channel-scale 0.5 \
  --epochs 6 --fov-epochs 2 --up-epochs 4 --up-extra 400 --root /tmp/rooms_seg --out /tmp/gpu_seg; }
det_recipe() { timeout 400 python3 -m usf_graph.cli train det --device cuda --channel-scale 0.5 \
  --epochs 16 --fov-epochs 3 --up-epochs 4 --up-extra 400 --root /tmp/rooms_det --out /tmp/gpu_det; }
case $RECIPE in
  seg) seg_recipe ;;
  det) det_recipe ;;
  both) seg_recipe > "$OUT/seg_recipe.log" 2>&1 & det_recipe; wait; tail -40 "$OUT/seg_recipe.log" ;;
  none) exit 0 ;;
  *) echo "RECIPE must be seg, det, both or none, got $RECIPE"; exit 2 ;;
esac
for r in seg det; do cp /tmp/gpu_$r/results.json "$OUT/${r}_results.json" 2>/dev/null; done
lap "$RECIPE recipe"
