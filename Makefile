# Every target sets up .venv (Python 3.11 + pip only) and installs the package on first use.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: setup demo test test-slow test-fast test-long lint bench bench-quick bench-full docs clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[test,docs]"
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(BIN)/python examples/quickstart.py

# pytest exits 5 when it collects nothing; make treats that as a failure.
# Test files are spread over PYTEST_WORKERS processes (pytest-xdist), one file per worker at
# a time so that a module's compiled solves are reused within it.
# `make test` runs every feature's tests but leaves out those marked `slow`: the further
# cases of a claim that a test in `make test` already makes (other problems, dtypes,
# activations, vmap of a solve whose single run is tested), each marked where it is with the
# test that keeps it covered. `make test-slow` runs them; CI (.ci/run) runs `make test` only.
PYTEST_WORKERS ?= 2
test: $(STAMP)
	$(BIN)/python -m pytest -q -n $(PYTEST_WORKERS) --dist loadfile -m "not slow and not long"

test-slow: $(STAMP)
	$(BIN)/python -m pytest -q -n $(PYTEST_WORKERS) --dist loadfile -m "slow and not long"

# `make test` in one process.
test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -m "not slow and not long"

# The studies marked `long` (tens of minutes; not part of `make test` or CI).
test-long: $(STAMP)
	$(BIN)/python -m pytest -q -m long

lint: $(STAMP)
	$(BIN)/ruff check diffrax_vi tests examples benchmarks

# The documentation site, built strictly (any warning fails) into site/, then the code blocks
# of the pages that `make test` leaves out (marked `long` in tests/test_docs_examples.py), so
# that `make docs` and `make test` together run every code block of the docs. Also installs
# Debian's chromium, which the browser test of the built site (tests/test_docs.py) needs.
docs: $(STAMP) /usr/bin/chromium
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict
	$(BIN)/python -m pytest -q -p no:cacheprovider tests/test_docs_examples.py -m long

/usr/bin/chromium:
	apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium

# Time per step against Dopri8 and the hardware's floor (docs/benchmarks.md).
bench: $(STAMP)
	$(BIN)/python -m benchmarks.step_floor --fresh 0 --repeats 5

# Work-precision, long-time energy and stability sweep (docs/benchmarks.md); results and
# figures go to benchmarks/results (quick) or benchmarks/results-full (full, hours).
bench-quick: $(STAMP)
	$(BIN)/python -m diffrax_vi.bench all --quick --jobs 2 --out benchmarks/results

bench-full: $(STAMP)
	$(BIN)/python -m diffrax_vi.bench all --full --jobs 2 --out benchmarks/results-full

clean:
	rm -rf $(VENV) build dist site *.egg-info .pytest_cache .ruff_cache tests/artifacts
