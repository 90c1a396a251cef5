# Two commands set everything up: `make demo` (the main job) and `make test`.
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: setup demo demo-det demo-seg info test test-slow lint bench clean
setup:
	@bash scripts/bootstrap.sh

info: setup
	@$(VENV)/bin/usf-graph info

demo: setup
	@$(VENV)/bin/usf-graph train mnist --out runs/mnist

# the detection protocol on procedural rooms (README, "Detection"): 31-32 min on sessions 23-24's 2 cores, rooms rendered
demo-det: setup
	@$(VENV)/bin/usf-graph train det --out runs/det

demo-seg: setup
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
