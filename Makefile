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

# tf2_msgs (the /tf message type) has no wheel: generated and compiled into the venv from its message
# definition with the ROS message generators the wheels ship (needs gcc/g++ and the Python headers).
# Without a compiler this step says why and the rest still works (map -> odom then only on pf/map_odom etc.).
TF2    := $(VENV)/.tf2_msgs
$(TF2): $(STAMP) indoor_loc/tools/build_tf2_msgs.py indoor_loc/data/tf2_msgs/msg/TFMessage.msg
	@if $(PY) -m indoor_loc.tools.build_tf2_msgs; then touch $(TF2); \
	else echo "make: tf2_msgs not built (see above); continuing without /tf output" >&2; fi

venv: $(STAMP) $(TF2)

# the main job on the shipped sample building: simulated walkers and a robot, every node live over DDS
# (no datasets needed)
demo: $(STAMP) $(TF2)
	$(VENV)/bin/indoor-loc demo --robots 1 --out $(OUT)/demo

# the same pipeline on the real PUTMC dataset (needs $(DATA)/putmc), replayed offline
demo-putmc: $(STAMP) $(TF2)
	$(VENV)/bin/indoor-loc demo --dataset putmc --data $(DATA) --out $(OUT)/demo_putmc

test: $(STAMP) $(TF2)
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
