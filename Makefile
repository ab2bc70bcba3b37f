# The two commands of the README. Each creates .venv when it is missing and installs
# bigT into it (editable), so they work on a machine that has only python3 and git;
# then bigT.warm compiles the numba kernels into their cache once (~20 s), so the first
# run does not wait for the compiler.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test test-all bench bench-quick clean

# numpy's huge-page advice off, as the bigT command sets it for itself
# (bigT.cli._advise_no_huge_pages): the tests and benchmarks that call the library in
# their own process run it as the command does
export NUMPY_MADVISE_HUGEPAGE ?= 0

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test]"
	$(BIN)/python -m bigT.warm
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/bigT demo

test: $(STAMP)
	$(BIN)/python -m pytest

# the default tests and the long ones (@pytest.mark.slow: every crash point, the
# larger stability sweeps)
test-all: $(STAMP)
	$(BIN)/python -m pytest -m "slow or not slow"

# every benchmark, about an hour: benchmarks/RESULTS.md and its plots in benchmarks/results/
# (ARGS passes options on: make bench ARGS="--only paper,scale"); bench-quick: small sizes
# in under 5 minutes, into bench-out/RESULTS.md (the committed results stay as they are).
# The full run refuses a tree with uncommitted changes (its results name the commit they
# come from): commit first, or pass ARGS=--allow-dirty to run anyway, marked as such
bench: $(STAMP)
	$(BIN)/python -m pip install --quiet -e ".[test,bench]"
	$(BIN)/python benchmarks/run_all.py $(ARGS)

bench-quick:
	$(MAKE) bench ARGS="--quick $(ARGS)"

clean:
	rm -rf $(VENV) build *.egg-info bigT-demo
