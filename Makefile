# Two commands on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
DATA   ?= ../shared/datasets
OUT    ?= out

.PHONY: demo demo-putmc test bench venv clean

$(STAMP): requirements.txt constraints.txt setup.py setup.cfg
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -r requirements.txt -c constraints.txt
	$(PY) -m pip install -q --no-deps -e .
	touch $(STAMP)

venv: $(STAMP)

# the main job on the shipped sample building: simulated walkers, every node live over DDS (no datasets needed)
demo: $(STAMP)
	$(VENV)/bin/indoor-loc demo --out $(OUT)/demo

# the same pipeline on the real PUTMC dataset (needs $(DATA)/putmc), replayed offline
demo-putmc: $(STAMP)
	$(VENV)/bin/indoor-loc demo --dataset putmc --data $(DATA) --out $(OUT)/demo_putmc

test: $(STAMP)
	$(PY) -m pytest -q -n 2 --timeout 300 test

# also run by `make test` (test/test_lint.py)
lint: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m mypy --config-file mypy.ini

bench: $(STAMP)
	$(VENV)/bin/indoor-loc bench imu --data $(DATA)
	$(VENV)/bin/indoor-loc bench wifi --data $(DATA)

clean:
	rm -rf $(VENV) $(OUT) build *.egg-info
