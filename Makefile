# Two commands set everything up: `make demo` (the main job) and `make test`.
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: setup demo demo-det demo-det-full demo-seg demo-seg-full protocols info test test-slow docs lint bench clean
# the 15-minute recipes (README, "Results in 15 minutes")
DET15 := --channel-scale 0.5 --epochs 16 --fov-epochs 3 --up-epochs 4 --up-extra 400
SEG15 := --channel-scale 0.5 --epochs 6 --fov-epochs 2 --up-epochs 4 --up-extra 400
MATERIALS ?= random
DEVICE ?= cpu
RUNS ?= runs/protocols_$(MATERIALS)
setup:
	@bash scripts/bootstrap.sh

info: setup
	@$(VENV)/bin/usf-graph info

demo: setup
	@$(VENV)/bin/usf-graph train mnist --out runs/mnist

# the detection protocol in 15 minutes: half the channels, 16 + 3 epochs (README, "Results in 15 minutes")
demo-det: setup
	@$(VENV)/bin/usf-graph train det $(DET15) --out runs/det_15min

# the full detection protocol (the README's tables): 31-32 min on sessions 23-24's 2 cores, rooms rendered
demo-det-full: setup
	@$(VENV)/bin/usf-graph train det --out runs/det

# the segmentation protocol in 15 minutes: half the channels, 6 + 2 epochs (README, "Results in 15 minutes")
demo-seg: setup
	@$(VENV)/bin/usf-graph train seg $(SEG15) --out runs/seg_15min

# the full segmentation protocol (the README's tables): about 42 min on 2 cores, rooms rendered
demo-seg-full: setup
	@$(VENV)/bin/usf-graph train seg --out runs/seg

# every run behind the README's "Where it stands" tables, then their targets: detection
# 15 minutes x seeds 0-4 and the full protocol, segmentation 15 minutes x seeds 0-2 and the
# full one (about 3.5 h on 2 cores). MATERIALS=by_kind: on rooms by kind; DEVICE=cuda: on a
# GPU. A run with results.json in $(RUNS) is kept, an interrupted one resumed.
protocols: setup
	@set -e; run() { d=$(RUNS)/$$1; shift; [ -f $$d/results.json ] || $(VENV)/bin/usf-graph train "$$@" \
	  --materials $(MATERIALS) --device $(DEVICE) --resume --out $$d; }; \
	for s in 0 1 2 3 4; do run det15_seed$$s det $(DET15) --seed $$s; done; run det_full det; \
	for s in 0 1 2; do run seg15_seed$$s seg $(SEG15) --seed $$s; done; run seg_full seg; \
	$(VENV)/bin/usf-graph targets $(RUNS)/det15_seed0 $(RUNS)/det15_seed1 $(RUNS)/det15_seed2 \
	  $(RUNS)/det15_seed3 $(RUNS)/det15_seed4 $(RUNS)/det_full; \
	$(VENV)/bin/usf-graph targets $(RUNS)/seg15_seed0 $(RUNS)/seg15_seed1 $(RUNS)/seg15_seed2 $(RUNS)/seg_full

# two worker processes (pytest-xdist), one torch thread each: 5 minutes where one took 8
test: setup
	@$(VENV)/bin/ruff check usf_graph tests examples benchmarks scripts
	@$(PY) -m pytest -n 2 --dist worksteal

# the API reference from the docstrings: docs/api/index.html (pdoc, about 10 s)
docs: setup
	@$(PY) scripts/api_docs.py --out docs/api

test-slow: setup
	@$(PY) -m pytest -m slow

bench: setup
	@$(PY) benchmarks/conv.py
	@$(PY) benchmarks/lift.py

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
