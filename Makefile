# ripplecal: `make run` starts the service on the emulated bench (`make run PORT=8001 HOST=127.0.0.1`
# to choose where it listens), `make test` runs the suite, `make bench` prints the performance figures,
# `make paper` reproduces the paper's Fig. 8-12 into build/paper/ (report.html, results.json).
# Each creates .venv and installs what is missing.
PYTHON ?= python3
# plain assignments: `make run PORT=...` overrides them, an exported HOST (the machine's name in
# some shells) does not
HOST := 127.0.0.1
PORT := 8000
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
CHROMIUM := /usr/bin/chromium

.PHONY: run test lint format bench paper venv chromium postgresql faketime clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

venv: $(STAMP)

# Debian's Chromium for the browser test (never a downloaded browser)
chromium:
	@test -x $(CHROMIUM) || { command -v apt-get >/dev/null && \
	  { [ "$$(id -u)" = 0 ] && SUDO= || SUDO=sudo; $$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq chromium; }; }

# Debian's PostgreSQL server binaries for the lab engine's tests (tests/support/postgres.py starts a
# throwaway cluster from them; the packaged cluster itself is not used)
postgresql:
	@ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1 || { command -v apt-get >/dev/null && \
	  { [ "$$(id -u)" = 0 ] && SUDO= || SUDO=sudo; $$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq postgresql; }; }

# Debian's libfaketime for the skewed-clock tests (tests/support/skewed_clock.py preloads it into one service,
# with a small C shim it compiles: gcc)
faketime:
	@{ ls /usr/lib/*/faketime/libfaketime.so.1 && command -v cc; } >/dev/null 2>&1 || { command -v apt-get >/dev/null && \
	  { [ "$$(id -u)" = 0 ] && SUDO= || SUDO=sudo; $$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq faketime gcc; }; }

run: $(STAMP)
	$(VENV)/bin/ripplecal serve --emulate --host $(HOST) --port $(PORT)

test: $(STAMP) chromium postgresql faketime lint
	$(PY) -m pytest -q --durations=30

# ruff: lint and format check; mypy: the type checker, strict on the packages pyproject.toml names
# (config of both in pyproject.toml); `make format` applies the formatter
lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy

format: $(STAMP)
	$(VENV)/bin/ruff format .
	$(VENV)/bin/ruff check --fix .

bench: $(STAMP)
	@for script in tests/benchmarks/bench_*.py; do echo "== $$script"; $(PY) -m tests.benchmarks.$$(basename $$script .py) || exit 1; done

paper: $(STAMP)
	$(VENV)/bin/ripplecal paper --out build/paper

clean:
	rm -rf $(VENV) data .pytest_cache build
