"""Print the interpreter, BLAS and the versions of the packages every figure depends on (one line each).

Run by `make test` and `.ci/run` first, so a red run says what it ran on.
"""
from __future__ import annotations

import platform
from importlib import metadata

PACKAGES = ("numpy", "scipy", "pin", "mujoco", "scikit-learn", "rosbags", "matplotlib", "example-robot-data",
            "pytest", "hypothesis")


def main() -> None:
    print(f"python {platform.python_version()} on {platform.system()} {platform.machine()}")
    found = []
    for name in PACKAGES:
        try:
            found.append(f"{name}=={metadata.version(name)}")
        except metadata.PackageNotFoundError:
            found.append(f"{name} (not installed)")
    print(" ".join(found))
    try:
        import numpy  # noqa: F401  (loads the BLAS that threadpoolctl reports)
        import scipy.linalg  # noqa: F401
        from threadpoolctl import threadpool_info
        print("blas/openmp: " + ", ".join(f"{pool.get('internal_api')} {pool.get('version')} "
                                          f"threads={pool.get('num_threads')}" for pool in threadpool_info()))
    except ImportError:
        print("blas/openmp: threadpoolctl not installed")


if __name__ == "__main__":
    main()
