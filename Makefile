# Two commands set everything up: `make demo` (the main job) and `make test`.
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: setup demo demo-det demo-det-full demo-seg demo-seg-full info test test-slow lint bench clean
setup:
	@bash scripts/bootstrap.sh

info: setup
	@$(VENV)/bin/usf-graph info

demo: setup
	@$(VENV)/bin/usf-graph train mnist --out runs/mnist

# the detection protocol in 15 minutes: half the channels, 16 + 3 epochs (README, "Results in 15 minutes")
demo-det: setup
	@$(VENV)/bin/usf-graph train det --channel-scale 0.5 --epochs 16 --fov-epochs 3 --up-epochs 4 --up-extra 400 --out runs/det_15min

# the full detection protocol (the README's tables): 31-32 min on sessions 23-24's 2 cores, rooms rendered
demo-det-full: setup
	@$(VENV)/bin/usf-graph train det --out runs/det

# the segmentation protocol in 15 minutes: half the channels, 6 + 2 epochs (README, "Results in 15 minutes")
demo-seg: setup
	@$(VENV)/bin/usf-graph train seg --channel-scale 0.5 --epochs 6 --fov-epochs 2 --up-epochs 4 --up-extra 400 --out runs/seg_15min

# the full segmentation protocol (the README's tables): about 42 min on 2 cores, rooms rendered
demo-seg-full: setup
	@$(VENV)/bin/usf-graph train seg --out runs/seg

test: setup
	@$(VENV)/bin/ruff check usf_graph tests examples benchmarks
	@$(PY) -m pytest

test-slow: setup
	@$(PY) -m pytest -m slow

bench: setup
	@$(PY) benchmarks/conv.py
	@$(PY) benchmarks/lift.py

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
