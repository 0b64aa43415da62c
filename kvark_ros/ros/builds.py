"""Building the node's estimator off its input path: a reload must not hold up the samples.

``build_off_path`` runs ``Estimator.from_config`` on a worker thread and returns an rclpy ``Future`` the
node's coroutine awaits, while the single-threaded executor keeps taking samples; the node then swaps the
new estimator in between two samples. The worker shares the interpreter with the executor, so
``SWITCH_INTERVAL`` bounds how long it holds it at a time (``main`` sets it), and BLAS runs one thread
(``one_blas_thread``).
"""
from __future__ import annotations

import threading
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from rclpy.task import Future
from threadpoolctl import threadpool_limits

from kvark_ros.core.config import EstimatorConfig
from kvark_ros.core.estimation.estimator import Estimator
from kvark_ros.core.estimation.wrench_output import WrenchOutput

if TYPE_CHECKING:
    from rclpy.executors import Executor

# s a build thread may hold the interpreter before the inputs get it: with Python's 0.005 a sample waited 8-13 ms
# at a time during a build, with 0.0002 mostly 1-2 ms (a few native calls hold it up to ~9 ms either way).
SWITCH_INTERVAL = 0.0002
BUILD_ERRORS = (ValueError, OSError, RuntimeError, KeyError, TypeError, np.linalg.LinAlgError)


class Built(NamedTuple):
    """A new estimator and the frames, axes and sign its wrench is published in."""

    estimator: Estimator
    output: WrenchOutput


def one_blas_thread() -> None:
    """BLAS on one thread for the rest of the process (``main`` calls it first). The node's matrices are small, and
    OpenBLAS's second thread, waiting for a core the controller holds, made a reload's seven triangular solves (the
    KMP's factors) take 29 ms instead of 0.3 while samples waited. The figures do not change: one thread or two
    give the same bits on the committed bags."""
    threadpool_limits(limits=1)


def build(config: EstimatorConfig, urdf_xml: str | None) -> Built | str:
    """A new estimator of ``config`` (``urdf_xml``: the robot_description's URDF) and its wrench output, or the
    problem as text."""
    try:
        estimator = Estimator.from_config(config, urdf=urdf_xml)
        return Built(estimator, WrenchOutput(estimator.robot, config))
    except BUILD_ERRORS as exc:
        return str(exc) or type(exc).__name__


def build_off_path(executor: Executor | None, config: EstimatorConfig, urdf_xml: str | None) -> Future:
    """``build`` on a worker thread; await the returned Future for its result (an unexpected error is raised
    there: a bug, not a bad model)."""
    done = Future(executor=executor)
    done.add_done_callback(lambda _future: None)    # with a done callback, set_result wakes the executor

    def run() -> None:
        try:
            done.set_result(build(config, urdf_xml))
        except Exception as exc:
            done.set_exception(exc)

    threading.Thread(target=run, name="kvark_model_build", daemon=True).start()
    return done
