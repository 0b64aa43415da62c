"""The estimator compiles every numba kernel of its step when it is built, never on a sample.

On a cold numba cache (a fresh clone, a new install) a kernel compiled on the first sample stalled the ROS node ~0.4 s,
and its subscription dropped ~100 joint states at 500 Hz. Checked in a fresh interpreter, where no earlier test has
compiled anything: every numba dispatcher of the package holds the same signatures after 50 samples of a bag as
right after the estimator was built (loading machine code from the cache counts as built, so the check does not
depend on the cache being warm).
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
CHECK = """
import sys
import numba.core.registry
from kvark_ros.core.config import load_config
from kvark_ros.core.estimation.estimator import Estimator
from kvark_ros.core.estimation.model_store import load_model
from kvark_ros.io.recorded_inputs import read_inputs

def signatures():
    found = {}
    for name, module in list(sys.modules.items()):
        if name.startswith("kvark_ros."):
            for attribute, value in vars(module).items():
                if isinstance(value, numba.core.registry.CPUDispatcher):
                    found[f"{name}.{attribute}"] = len(value.signatures)
    return found

config = load_config("config/panda.yaml")
trained = load_model(config.model_dir, config.joint_names)
inputs = read_inputs("bags/panda_contact", config)[1]
estimator = Estimator.from_config(config, trained, sys.argv[1])
built = signatures()
for k in range(50):
    estimator.step(inputs.stamp[k], inputs.q[k], inputs.qd[k], inputs.tau_m[k])
after = signatures()
print({name: (built.get(name, 0), count) for name, count in after.items() if count != built.get(name, 0)})
"""


@pytest.mark.parametrize("observer", ["kvark", "momentum"])
def test_no_kernel_compiles_on_a_sample(observer):
    """The compiled K-VARK step and a numpy-path observer (momentum): no dispatcher gains a signature while stepping."""
    result = subprocess.run([sys.executable, "-c", CHECK, observer], cwd=ROOT, capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.strip().splitlines()[-1] == "{}", result.stdout
