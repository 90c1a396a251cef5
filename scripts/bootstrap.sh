#!/usr/bin/env bash
# Creates or refreshes the project-local .venv. Idempotent: when the stamp matches the
# inputs (pyproject.toml, this script) it returns in well under a second.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
PY=${PYTHON:-python3}
TORCH_VERSION=2.13.0
stamp="$VENV/.usf-graph-stamp"
want=$(cat pyproject.toml scripts/bootstrap.sh | sha256sum | cut -d' ' -f1)
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] && [ -x "$VENV/bin/python" ]; then
  exit 0
fi
say() { printf '\033[1m[setup]\033[0m %s\n' "$*"; }
if [ ! -x "$VENV/bin/python" ]; then
  say "creating $VENV with $($PY --version)"
  "$PY" -m venv "$VENV"
fi
pip=("$VENV/bin/python" -m pip --disable-pip-version-check)
# A constraints file keeps every later resolve on the CPU torch we install first:
# letting pip pick torch would pull several GB of CUDA packages.
constraints="$VENV/constraints.txt"
echo "torch==$TORCH_VERSION" > "$constraints"
export PIP_CONSTRAINT="$PWD/$constraints"
if ! "$VENV/bin/python" -c "import torch, sys; sys.exit(torch.__version__.split('+')[0] != '$TORCH_VERSION')" 2>/dev/null; then
  say "installing torch==$TORCH_VERSION (CPU)"
  "${pip[@]}" install -q "torch==$TORCH_VERSION"
fi
"${pip[@]}" install -q wheel setuptools ninja
missing=()
"$VENV/bin/python" -c "import torch_scatter" 2>/dev/null || missing+=(torch-scatter==2.1.2)
"$VENV/bin/python" -c "import torch_cluster" 2>/dev/null || missing+=(torch-cluster==1.6.3)
if [ ${#missing[@]} -gt 0 ]; then
  say "building ${missing[*]} from source against torch $TORCH_VERSION."
  say "First time on a machine this takes 15-25 minutes on 2 cores; pip caches the wheels,"
  say "so later set-ups take seconds. Progress: pip's build log follows."
  MAX_JOBS=${MAX_JOBS:-$(nproc)} "${pip[@]}" install --no-build-isolation -v "${missing[@]}" 2>&1 \
    | grep --line-buffered -E "(building '|Building wheel|Created wheel|Successfully|Using cached|ERROR|error:)" || true
  "$VENV/bin/python" -c "import torch_scatter, torch_cluster" \
    || { echo "torch-scatter/torch-cluster failed to build; see the log above" >&2; exit 1; }
fi
say "installing usf-graph (editable) with its test, demo and export extras"
"${pip[@]}" install -q -e ".[test,demo,export]"
echo "$want" > "$stamp"
say "done: $("$VENV/bin/python" -c 'import torch, torch_geometric; print("torch", torch.__version__, "| torch_geometric", torch_geometric.__version__)')"
