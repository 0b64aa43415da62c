# kvark_ros developer entry points. Each target creates .venv on first use and installs into it
# the exact versions of requirements-lock.txt, then the package itself (editable, no dependency
# resolution), so every machine runs what the lock says. `make lock` refreshes the lock;
# `make test-newest` runs the suite on the newest releases instead.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.kvark-installed
LOCK   := requirements-lock.txt
PIP_VERSION := 26.3
UV_VERSION  := 0.13.9
# One thread per BLAS/OpenMP pool: figures and tests do not depend on the machine's core count.
export OMP_NUM_THREADS := 1
export OPENBLAS_NUM_THREADS := 1
export MKL_NUM_THREADS := 1

.PHONY: demo docs docs-check test test-newest smoke-newest smoke-newest-only smoke-newest-cli smoke-newest-tests newest-venv lock versions bench bags model benchmark reliability clean \
  generated

KVARK   := $(BIN)/kvark
CONFIG  := config/panda.yaml
PLANT   := kvark_ros/sim/plants/panda_default.yaml
SCENES  := payload contact collision
RESULTS ?= results

$(STAMP): setup.py setup.cfg $(LOCK)
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 10) else "kvark_ros needs Python 3.10 or newer")'
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet pip==$(PIP_VERSION)
	$(BIN)/python -m pip install --quiet -r $(LOCK)
	$(BIN)/python -m pip install --quiet --no-deps -e .
	$(BIN)/python -m pip check
	touch $(STAMP)

## demo: the main job on a laptop (no robot, no ROS install): committed bags -> diagnose the model gap ->
## train on the augmented model -> replay every observer -> run the ROS 2 node (the lock's rclpy wheels)
## on a bag over loopback DDS, a reload mid-run, and print how it matches replay
TRAIN_BAGS := bags/panda_excitation_1 bags/panda_excitation_2
demo: $(STAMP)
	$(KVARK) diagnose --config $(CONFIG) --bags $(TRAIN_BAGS) --out $(RESULTS)/diagnosis --force
	$(KVARK) train --config $(CONFIG) --bags $(TRAIN_BAGS) --augmentation $(RESULTS)/diagnosis/augmentation.yaml \
	  --out $(RESULTS)/model --force
	for scene in $(SCENES); do \
	  $(KVARK) replay --config $(CONFIG) --model $(RESULTS)/model --bag bags/panda_$$scene \
	    --observers all --plant $(PLANT) --out $(RESULTS)/$$scene --force || exit 1; \
	done
	$(KVARK) node-check --config $(CONFIG) --model $(RESULTS)/model --bag bags/panda_contact --reload-at 2.5
	@echo "demo: the model gap in $(RESULTS)/diagnosis/report.md, the model in $(RESULTS)/model, each scene's report and plots in $(RESULTS)/<scene>/"
	@$(BIN)/python scripts/demo_table.py $(RESULTS)

## bags: regenerate the committed sample bags (simulated Panda)
bags: $(STAMP)
	$(KVARK) simulate --robot panda --scenario excitation --seed 1 --duration 8 --out bags/panda_excitation_1 --force
	$(KVARK) simulate --robot panda --scenario excitation --seed 2 --duration 8 --out bags/panda_excitation_2 --force
	for scene in $(SCENES); do \
	  $(KVARK) simulate --robot panda --scenario $$scene --seed 3 --duration 5 --out bags/panda_$$scene --force || exit 1; \
	done

## model: retrain the committed model from the committed bags
model: $(STAMP)
	$(KVARK) train --config $(CONFIG) --bags $(TRAIN_BAGS) --out models/panda --force

## reliability: the reliability figures: a 10^6-step soak with faults and the property tests
reliability: $(STAMP)
	$(KVARK) soak --steps 1000000
	$(BIN)/python -m pytest test/core/test_bad_input_properties.py -q --hypothesis-show-statistics

## benchmark: the full simulated comparison of every observer (see README, Results)
benchmark: $(STAMP)
	$(KVARK) benchmark --robot panda --out $(RESULTS)/benchmark --force

## test: the whole test suite, on the locked versions: TEST_WORKERS processes, one test file each at a time, then
## the tests marked realtime (a node process keeping up with a bag's real rate) alone
TEST_WORKERS ?= 2
PYTEST_SPLIT = -q -n $(TEST_WORKERS) --dist loadfile -m "not realtime"
test: $(STAMP)
	@$(BIN)/python test/versions.py
	$(BIN)/python -m pytest $(PYTEST_SPLIT)
	$(BIN)/python -m pytest -q -m realtime

## docs: re-measure every figure of docs/results.md (and README's results at a glance, docs/walkthrough.md's
## tables, README's picture) by running the commands that produce them (about 15 min on 2 cores)
docs: $(STAMP)
	PATH="$(abspath $(BIN)):$$PATH" $(BIN)/python scripts/results_doc.py

## docs-check: run every `bash` block of README.md and docs/*.md as written, after the quick start, in a scratch
## copy of the project (CI runs it)
docs-check: $(STAMP)
	PATH="$(abspath $(BIN)):$$PATH" $(BIN)/python scripts/check_docs_commands.py

## generated: after a change to the key table (kvark_ros/core/config_schema.py), write what it generates: the typed
## settings (kvark_ros/core/settings.py), the key comments of config/*.yaml (values, notes and prose kept) and
## the table of keys in docs/configuration.md
generated: $(STAMP)
	$(BIN)/python -m kvark_ros.tools.generate_sources --write-settings --write-configs --write-keys-doc docs/configuration.md

## versions: the interpreter and the installed versions the figures depend on
versions: $(STAMP)
	@$(BIN)/python test/versions.py

## lock: refresh requirements-lock.txt (newest releases that install on Python 3.10-3.12 as one set;
## pytest stays below 9 because ROS 2 Jazzy's launch_testing plugin fails to load under pytest 9),
## reinstall .venv from it and run the suite
lock:
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet uv==$(UV_VERSION)
	$(BIN)/uv pip compile setup.cfg --extra sim --extra test --extra ros --universal --python-version 3.10 \
	  --fork-strategy fewest --upgrade --quiet -o $(LOCK)
	rm -f $(STAMP)
	$(MAKE) test

## test-newest: the suite on the newest releases the package's ranges allow (no lock), in .venv-newest
NEWEST := .venv-newest/bin
SMOKE  ?= /tmp/kvark-smoke-newest
newest-venv:
	test -x $(NEWEST)/python || $(PYTHON) -m venv .venv-newest
	$(NEWEST)/python -m pip install --quiet --upgrade pip
	$(NEWEST)/python -m pip install --quiet --upgrade --upgrade-strategy eager -e '.[sim,test,ros]'
	@$(NEWEST)/python test/versions.py

test-newest: newest-venv
	$(NEWEST)/python -m pytest $(PYTEST_SPLIT)
	$(NEWEST)/python -m pytest -q -m realtime

## smoke-newest: what CI runs on the newest releases within its budget: train and replay on the committed
## bags, the training and model-loading tests, and the real ROS 2 node on a bag (with a reload);
## smoke-newest-only: the same on .venv-newest as it is (CI installs it while the suite runs). The command-line
## train and replay run beside the training tests (one process each); the real node's tests run alone after.
smoke-newest: newest-venv
	$(MAKE) smoke-newest-only
smoke-newest-only:
	test -x $(NEWEST)/kvark || { echo "no .venv-newest: run make smoke-newest"; exit 1; }
	$(MAKE) --no-print-directory -j2 --output-sync=target smoke-newest-cli smoke-newest-tests
	$(NEWEST)/python -m pytest -q test/ros/test_node_under_rclpy.py
smoke-newest-cli:
	rm -rf $(SMOKE)
	$(NEWEST)/kvark train --config $(CONFIG) --bags $(TRAIN_BAGS) --out $(SMOKE)/model
	$(NEWEST)/kvark replay --config $(CONFIG) --model $(SMOKE)/model --bag bags/panda_contact --no-bag \
	  --out $(SMOKE)/contact
smoke-newest-tests:
	$(NEWEST)/python -m pytest -q test/tools/test_train_and_replay.py test/core/test_kmp_residual.py

## bench: per-step latency of every observer
bench: $(STAMP)
	$(BIN)/kvark bench --robot panda --observer all

clean:
	rm -rf $(VENV) .venv-newest build *.egg-info .pytest_cache
