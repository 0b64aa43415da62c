# kvark_ros developer entry points. Each target creates .venv on first use and installs
# the package (editable, with the simulator and test extras) into it.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.kvark-installed

.PHONY: demo test bench bags model benchmark reliability clean

KVARK   := $(BIN)/kvark
CONFIG  := config/panda.yaml
PLANT   := kvark_ros/sim/plants/panda_default.yaml
SCENES  := payload contact collision
RESULTS ?= results

$(STAMP): setup.py setup.cfg
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 10) else "kvark_ros needs Python 3.10 or newer")'
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[sim,test]'
	touch $(STAMP)

## demo: the main job on a laptop (no robot, no ROS): committed bags -> diagnose the model gap ->
## train on the augmented model -> replay every observer
TRAIN_BAGS := bags/panda_excitation_1 bags/panda_excitation_2
demo: $(STAMP)
	$(KVARK) diagnose --config $(CONFIG) --bags $(TRAIN_BAGS) --out $(RESULTS)/diagnosis
	$(KVARK) train --config $(CONFIG) --bags $(TRAIN_BAGS) --augmentation $(RESULTS)/diagnosis/augmentation.yaml \
	  --out $(RESULTS)/model
	for scene in $(SCENES); do \
	  $(KVARK) replay --config $(CONFIG) --model $(RESULTS)/model --bag bags/panda_$$scene \
	    --observers all --plant $(PLANT) --out $(RESULTS)/$$scene || exit 1; \
	done
	@echo "demo results: $(RESULTS)/diagnosis/report.md (model gap), $(RESULTS)/<scenario>/report.md, metrics.json, plots; model in $(RESULTS)/model"

## bags: regenerate the committed sample bags (simulated Panda)
bags: $(STAMP)
	$(KVARK) simulate --robot panda --scenario excitation --seed 1 --duration 8 --out bags/panda_excitation_1 --overwrite
	$(KVARK) simulate --robot panda --scenario excitation --seed 2 --duration 8 --out bags/panda_excitation_2 --overwrite
	for scene in $(SCENES); do \
	  $(KVARK) simulate --robot panda --scenario $$scene --seed 3 --duration 5 --out bags/panda_$$scene --overwrite || exit 1; \
	done

## model: retrain the committed model from the committed bags
model: $(STAMP)
	$(KVARK) train --config $(CONFIG) --bags $(TRAIN_BAGS) --out models/panda

## reliability: the reliability figures: a 10^6-step soak with faults and the property tests
reliability: $(STAMP)
	$(KVARK) soak --steps 1000000
	$(BIN)/python -m pytest test/test_reliability.py -q --hypothesis-show-statistics

## benchmark: the full simulated comparison of every observer (see README, Results)
benchmark: $(STAMP)
	$(KVARK) benchmark --robot panda --out $(RESULTS)/benchmark

## test: the whole test suite
test: $(STAMP)
	$(BIN)/python -m pytest -q

## bench: per-step latency of every observer
bench: $(STAMP)
	$(BIN)/kvark bench --robot panda --observer all

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
