# Every user-facing target bootstraps its own environment first (make setup is idempotent).
PYTHON ?= python3
VENV := .venv
VPY := $(VENV)/bin/python
STAMP := $(VENV)/.setup-done
DATA ?=
PYTEST_ARGS ?=

.PHONY: setup demo test bench clean

setup: $(STAMP)

$(STAMP): setup.py package.xml scripts/setup_env.sh
	PYTHON=$(PYTHON) bash scripts/setup_env.sh $(VENV)
	touch $(STAMP)

demo: setup
	$(VENV)/bin/mf-lpr demo $(if $(DATA),--data $(DATA),)

test: setup
	$(VPY) -m pytest -q $(PYTEST_ARGS)

bench: setup
	$(VPY) benchmarks/bench_search.py

clean:
	rm -rf $(VENV) build install log *.egg-info
