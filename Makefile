# The two commands: `make demo` and `make test`. Each sets up .venv on first use.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint typecheck unit integration contract bench clean

# uv installs what pip would (the same versions from PyPI) in about 15 s against pip's 45 to 60 on
# this machine: it fetches in parallel and compiles the bytecode on every core. uv does not read
# pip.conf; a mirror or an extra index is set for it with UV_INDEX_URL or UV_EXTRA_INDEX_URL.
$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check uv
	$(BIN)/uv pip install --quiet --python $(BIN)/python --compile-bytecode -e '.[dev]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/tether demo

# The suite sized for two cores (tests/suite.py): the wall-clock tests (`-m realtime`) one at a time
# at normal priority, beside the tests that start services on three pytest-xdist workers at low
# priority; then the tests marked `alone` (multi-host, ROS 2 stand-in, robot contract) one at a time,
# without other stacks, with the unit tests (`-m unit`, all of tests/unit) on two workers at the lowest
# priority; from the start, on idle CPU, the unit tests that only compute (`-m idle`) and mypy
# (`make typecheck`). The bytecode is compiled once up front: with PYTHONDONTWRITEBYTECODE set, every
# service process would compile again (and the suite lets pytest keep its assert-rewritten test
# modules, tests/suite.py). Given no paths, each run collects only the directories its tests can be in
# (tests/suite.py ROOTS).
test: $(STAMP) lint
	$(BIN)/python -m compileall -q -j 0 schemas services tether tests bench
	$(BIN)/python -m tests.suite --typecheck

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

typecheck: $(STAMP)
	$(BIN)/mypy

unit: $(STAMP)
	$(BIN)/python -m pytest -q tests/unit

integration: $(STAMP)
	$(BIN)/python -m pytest -q tests/integration

# docs/robot.md against every robot backend (tests/robot_contract/conftest.py: BACKENDS).
contract: $(STAMP)
	$(BIN)/python -m pytest -q tests/robot_contract

bench: $(STAMP)
	$(BIN)/python -m bench.transport --json

clean:
	rm -rf $(VENV) .mypy_cache .pytest_cache .ruff_cache recordings
