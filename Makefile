# Every user-facing target bootstraps its own environment first (make setup is idempotent).
PYTHON ?= python3
VENV := .venv
VPY := $(VENV)/bin/python
STAMP := $(VENV)/.setup-done
DATA ?=
PYTEST_ARGS ?=

TORCH_STAMP := $(VENV)/.torch-done
BASELINES_STAMP := $(VENV)/.baselines-done

.PHONY: setup torch baselines demo test bench clean

setup: $(STAMP)

# PyTorch's CPU build, only so that the tests check the torch backend against numpy. A local
# wheel where this machine image keeps one, else the CPU index; without either the torch tests skip.
torch: $(TORCH_STAMP)

$(TORCH_STAMP): $(STAMP)
	if ls /opt/wheels/torch-2.13.0*cpu*.whl >/dev/null 2>&1; then \
	  $(VPY) -m pip install -q torch==2.13.0; \
	else \
	  $(VPY) -m pip install -q --retries 0 --timeout 20 torch \
	    --index-url https://download.pytorch.org/whl/cpu; \
	fi || echo "setup: PyTorch not installed; the torch backend's tests will be skipped"
	touch $(TORCH_STAMP)

# The MapClosures baseline (mf-lpr compare/suite --methods map-closures). Without its
# dependencies: they would pin an older numpy, and only its pybind core and pydantic are needed.
baselines: $(BASELINES_STAMP)

$(BASELINES_STAMP): $(STAMP)
	{ $(VPY) -m pip install -q --retries 0 --timeout 20 --no-deps map-closures \
	  && $(VPY) -m pip install -q --retries 0 --timeout 20 pydantic; } \
	  || echo "setup: map-closures not installed; its baseline tests will check the refusal"
	touch $(BASELINES_STAMP)

$(STAMP): setup.py package.xml scripts/setup_env.sh
	PYTHON=$(PYTHON) bash scripts/setup_env.sh $(VENV)
	touch $(STAMP)

demo: setup
	$(VENV)/bin/mf-lpr demo $(if $(DATA),--data $(DATA),)

# Lint first (pyflakes errors, syntax errors, lines over the project's 100 columns), then the tests
# in two worker processes, a test file's tests in one (module fixtures are built once), each
# worker on a DDS domain of its own (test/conftest.py); then, alone, the tests that stream at a
# fixed rate (marker realtime). 12 min -> ~10 on two cores. Exit status 5: none selected.
TEST_PROCESSES ?= 2
test: setup torch baselines
	$(VENV)/bin/ruff check mf_lpr_ros test benchmarks launch
	MF_LPR_TEST_PHASE=parallel $(VPY) -m pytest -q -n $(TEST_PROCESSES) --dist loadfile \
	  $(PYTEST_ARGS) || [ $$? -eq 5 ]
	MF_LPR_TEST_PHASE=realtime $(VPY) -m pytest -q $(PYTEST_ARGS) || [ $$? -eq 5 ]

bench: setup
	$(VPY) benchmarks/bench_search.py

clean:
	rm -rf $(VENV) build install log *.egg-info
