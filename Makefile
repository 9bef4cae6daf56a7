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

.PHONY: run test bench paper venv chromium clean

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

run: $(STAMP)
	$(VENV)/bin/ripplecal serve --emulate --host $(HOST) --port $(PORT)

test: $(STAMP) chromium
	$(PY) -m pytest -q

bench: $(STAMP)
	@for script in tests/benchmarks/bench_*.py; do echo "== $$script"; $(PY) -m tests.benchmarks.$$(basename $$script .py) || exit 1; done

paper: $(STAMP)
	$(VENV)/bin/ripplecal paper --out build/paper

clean:
	rm -rf $(VENV) data .pytest_cache build
