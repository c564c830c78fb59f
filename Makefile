# posegrid: every target creates .venv and installs the project when needed, so a fresh clone works. The install
# ends by compiling the numba kernels into their cache (services/commands/warm_kernels.py, about a minute on 2
# cores), so that the first `make run` and the test suite do not wait for the compiler.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: install run test lint bench clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	$(PY) -m services.commands.warm_kernels
	touch $(STAMP)

install: $(STAMP)

## make run: the whole pipeline on the built-in simulated world; prints where to look. Options of posegrid run
## go in RUN_ARGS, e.g. make run RUN_ARGS="--api-port 8001"
run: $(STAMP)
	$(VENV)/bin/posegrid run $(RUN_ARGS)

## make test: the test suite on every core (pytest-xdist, two workers more than the cores: many tests wait on the
## processes they start, and the extra workers fill those waits: on 2 cores 4 workers took 307-334 s where 3 took
## 368-402 s in the same hours, the CPUs then 85 % busy; a worker that runs out of tests takes some of another's,
## --dist worksteal, so they finish together; pytest's exit 5, "no tests collected", fails the target and says so).
## One file alone: .venv/bin/python -m pytest tests/test_x.py. Bytecode is cached (in the checkout's __pycache__
## folders, even where PYTHONDONTWRITEBYTECODE is set): the suite starts a few hundred processes, and each would
## compile the project's sources again (0.3 CPU s a service, 6 s for a worker's collection)
test: $(STAMP)
	@env -u PYTHONDONTWRITEBYTECODE $(PY) -m pytest -q -n $$(( $$(nproc) + 2 )) --dist worksteal; rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "make test: pytest collected no tests (exit 5): that is a failure" >&2; fi; \
	exit $$rc

## make lint: ruff's rules and format, and mypy, as configured in pyproject.toml (CI runs it before the tests)
lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy

## make bench: benchmarks; JSON under bench/results/, a table on stdout
bench: $(STAMP)
	$(PY) -m pip install --quiet -e '.[bench]' || echo 'pyoctomap not installed: the OctoMap columns will be skipped'
	$(PY) -m bench.run

## make clean: the virtual environment, build and benchmark outputs, and the bytecode and numba kernel caches
## (nothing needs it after an edit: a kernel's cache follows every module it imports, mapping/jit.py)
clean:
	rm -rf $(VENV) build *.egg-info bench/results .pytest_cache
	find mapping slam -name __pycache__ -prune -exec rm -rf {} +
