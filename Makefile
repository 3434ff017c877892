# The two commands a new user runs (see README.md):
#   make demo   set up .venv and run the main job on a small embedded default
#   make test   set up .venv and run the test suite
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.setup-stamp

.PHONY: setup demo test bench clean-data

setup: $(STAMP)

$(STAMP): requirements.txt pyproject.toml scripts/setup.sh scripts/torch_cluster_subset.py
	VENV=$(VENV) bash scripts/setup.sh
	touch $(STAMP)

demo: setup
	$(PY) -m ggns demo

test: setup
	$(PY) -m pytest -q -n auto --dist loadgroup --durations=30

bench: setup
	$(PY) -m ggns bench sim --generate

clean-data:
	rm -rf data/plate_small data/plate_tiny data/tissue_demo
