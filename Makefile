# kvark_ros developer entry points. Each target creates .venv on first use and installs
# the package (editable, with the simulator and test extras) into it.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.kvark-installed

.PHONY: demo test bench clean

$(STAMP): setup.py setup.cfg
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 10) else "kvark_ros needs Python 3.10 or newer")'
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[sim,test]'
	touch $(STAMP)

## demo: the main job on a laptop (no robot, no ROS)
demo: $(STAMP)
	$(BIN)/kvark bench --robot panda --observer all

## test: the whole test suite
test: $(STAMP)
	$(BIN)/python -m pytest -q

## bench: per-step latency of every observer
bench: $(STAMP)
	$(BIN)/kvark bench --robot panda --observer all

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
