# Every target sets up .venv (Python 3.11 + pip only) and installs the package on first use.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: setup demo test test-fast test-long lint bench bench-quick bench-full clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[test]"
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(BIN)/python examples/quickstart.py

# pytest exits 5 when it collects nothing; make treats that as a failure.
test: $(STAMP)
	$(BIN)/python -m pytest -q

test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -m "not slow and not long"

# The studies marked `long` (tens of minutes; not part of `make test` or CI).
test-long: $(STAMP)
	$(BIN)/python -m pytest -q -m long

lint: $(STAMP)
	$(BIN)/ruff check diffrax_vi tests examples benchmarks

bench: $(STAMP)
	$(BIN)/python benchmarks/step_cost.py

# Work-precision, long-time energy and stability sweep (docs/benchmarks.md); results and
# figures go to benchmarks/results (quick) or benchmarks/results-full (full, hours).
bench-quick: $(STAMP)
	$(BIN)/python -m diffrax_vi.bench all --quick --out benchmarks/results

bench-full: $(STAMP)
	$(BIN)/python -m diffrax_vi.bench all --full --out benchmarks/results-full

clean:
	rm -rf $(VENV) build dist *.egg-info .pytest_cache .ruff_cache
