# Quick start: `make demo` runs the whole job on the simulated rig; `make test` runs the suite.
# Both do their own set-up (apt libllvm19 + libusb, a virtual environment, the packages).
VENV ?= .venv
STAMP := $(VENV)/.installed
DEMO_OUT ?= demo-out

.PHONY: demo test bench setup clean

$(STAMP): pyproject.toml constraints.txt scripts/setup.sh
	VENV=$(VENV) ./scripts/setup.sh

setup: $(STAMP)

demo: $(STAMP)
	VENV=$(VENV) DEMO_OUT=$(DEMO_OUT) ./scripts/demo.sh

# --durations: the slowest tests in every CI log, to see where its time grows.
# -n: pytest-xdist workers. Two on the 2-core CI machine took the suite from 18 to 10 minutes
# (session 49): much of a test's time is single-threaded (Dr.Jit tracing and LLVM compiling,
# numpy, the CLI's start-up), which a second process overlaps with another's renders.
TEST_WORKERS ?= 2
test: $(STAMP)
	$(VENV)/bin/python -m pytest -q -p no:cacheprovider -n $(TEST_WORKERS) --durations=15

bench: $(STAMP)
	$(VENV)/bin/python benchmarks/run_all.py

clean:
	rm -rf $(VENV) $(DEMO_OUT) .pytest_cache .hypothesis
