# posegrid: every target creates .venv and installs the project when needed, so a fresh clone works.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: install run test bench clean clean-cache

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

## make run: the whole pipeline on the built-in simulated world; prints where to look. Options of posegrid run
## go in RUN_ARGS, e.g. make run RUN_ARGS="--api-port 8001"
run: $(STAMP)
	$(VENV)/bin/posegrid run $(RUN_ARGS)

## make test: the test suite (pytest's exit 5, "no tests collected", fails the target)
test: $(STAMP)
	$(PY) -m pytest -q

## make bench: benchmarks; JSON under bench/results/, a table on stdout
bench: $(STAMP)
	$(PY) -m pip install --quiet -e '.[bench]' || echo 'pyoctomap not installed: the OctoMap columns will be skipped'
	$(PY) -m bench.run

## make clean-cache: numba's compiled kernels (mapping/, slam/). Needed after editing a helper that kernels in other
## files inline (raytrace, window_walk, free_runs, beam_model): numba's cache notices a change in a kernel's own
## file only, and would go on running the old helper
clean-cache:
	find mapping slam -name __pycache__ -prune -exec rm -rf {} +

clean: clean-cache
	rm -rf $(VENV) build *.egg-info bench/results .pytest_cache
