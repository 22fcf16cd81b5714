# Two commands on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
DATA   ?= ../shared/datasets
OUT    ?= out

.PHONY: demo test bench venv clean

$(STAMP): requirements.txt constraints.txt setup.py setup.cfg
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -r requirements.txt -c constraints.txt
	$(PY) -m pip install -q --no-deps -e .
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/indoor-loc demo --data $(DATA) --out $(OUT)/demo

test: $(STAMP)
	$(PY) -m pytest -q -n 2 --timeout 300 test

bench: $(STAMP)
	$(VENV)/bin/indoor-loc bench imu --data $(DATA)
	$(VENV)/bin/indoor-loc bench wifi --data $(DATA)

clean:
	rm -rf $(VENV) $(OUT) build *.egg-info
