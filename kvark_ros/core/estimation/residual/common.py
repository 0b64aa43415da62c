"""Conventions every residual model shares: variance floor, input checks, batch size, BLAS threads, and the
worker processes that fit the joints in parallel."""

from __future__ import annotations

import contextlib
import functools
import multiprocessing
import os
import signal
import sys
from concurrent.futures import Executor, ProcessPoolExecutor
from typing import Any, Callable, Iterator, Sequence, TypeVar

import numpy as np
from threadpoolctl import threadpool_limits

from kvark_ros.core.estimation.linalg import single_threaded_blas

Result = TypeVar("Result")

# Smallest predictive variance returned (N²·m²): eq. 23 (and the GP variances) is a difference of
# two nearly equal numbers near the data and round-off can push it slightly below zero.
VARIANCE_FLOOR = 1e-12
# Query rows per chunk in predict_batch: bounds the (chunk, n, N) temporaries to a few MB.
BATCH_CHUNK = 4096


def check_training_data(qd: np.ndarray, tau_r: np.ndarray, n_components: int,
                        n_support: int) -> tuple[np.ndarray, np.ndarray]:
    """Validate training data and settings; return qd, tau_r as float64 arrays (T, n)."""
    if n_components < 1:
        raise ValueError(f"n_components must be >= 1, got {n_components}")
    if n_support < 2:
        raise ValueError(f"n_support must be >= 2, got {n_support}")
    qd = np.asarray(qd, dtype=np.float64)
    tau_r = np.asarray(tau_r, dtype=np.float64)
    if qd.ndim != 2 or qd.shape != tau_r.shape:
        raise ValueError(
            f"qd and tau_r must both have shape (T, n); got {qd.shape} and {tau_r.shape}")
    for name, array in (("qd", qd), ("tau_r", tau_r)):
        bad = ~np.isfinite(array)
        if np.any(bad):
            joints = np.flatnonzero(bad.any(axis=0)).tolist()
            raise ValueError(
                f"{name} contains {int(bad.sum())} NaN/Inf value(s) (joints {joints}); "
                "remove or interpolate them before fitting")
    n_samples = qd.shape[0]
    if n_samples < 5 * n_components:
        raise ValueError(
            f"too few samples to fit a {n_components}-component GMM: got {n_samples}, "
            f"need at least {5 * n_components}")
    still = np.flatnonzero(np.ptp(qd, axis=0) == 0.0)
    if still.size:
        raise ValueError(
            f"joint(s) {still.tolist()} never move in the training data (constant velocity); "
            "their residual cannot be modelled as a function of velocity")
    return qd, tau_r


def check_samples(qd: np.ndarray, tau_r: np.ndarray, minimum: int,
                  what: str) -> tuple[np.ndarray, np.ndarray]:
    """Shape/finiteness/moving-joint checks of check_training_data, plus a minimum sample count."""
    n_samples = np.shape(qd)[0] if np.ndim(qd) == 2 else 0
    if np.ndim(qd) == 2 and n_samples < minimum:
        raise ValueError(f"too few samples to fit {what}: got {n_samples}, need at least {minimum}")
    # n_components=1, n_support=2: only the generic checks of check_training_data apply.
    return check_training_data(qd, tau_r, n_components=1, n_support=2)


def check_batch(qd: np.ndarray, n_joints: int) -> np.ndarray:
    """qd as a float64 (T, n_joints) array for predict_batch; ValueError for another shape."""
    qd = np.asarray(qd, dtype=np.float64)
    if qd.ndim != 2 or qd.shape[1] != n_joints:
        raise ValueError(f"qd must have shape (T, {n_joints}), got {qd.shape}")
    return qd


def single_threaded(func: Callable) -> Callable:
    """Run `func` (a fit, or a constructor that factorises) with BLAS/OpenMP limited to one
    thread.

    Constructors too: the factors then do not depend on the caller's thread pool, so a model
    rebuilt by load() predicts bit for bit what the fitted model predicted.

    The matrices here are small (≤ 1000², 50 × T, 30 × 30); see ``single_threaded_blas``.
    """
    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        with single_threaded_blas():
            return func(*args, **kwargs)
    return wrapper


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity), the default number of training workers."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:          # no sched_getaffinity (macOS, Windows)
        return os.cpu_count() or 1


def _start_worker() -> None:
    """Every worker: BLAS/OpenMP one thread (the fits are small, and results must not depend on the core count), and
    Ctrl-C left to the parent, which cancels the queued fits and waits for the running ones."""
    threadpool_limits(limits=1)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@contextlib.contextmanager
def joint_workers(jobs: int | None, tasks: int) -> Iterator[Executor | None]:
    """Worker processes for ``submit_joints`` and ``map_joints``: ``jobs`` of them (None: ``available_cores``), at most
    ``tasks``; None (fit here, one after the other) for one job.

    On Linux the workers are forked: a spawned worker re-imports numpy, scipy and scikit-learn (about 0.9 s of CPU
    each, measured), more than a joint's fit. On leaving, fits not yet started are cancelled (an error or Ctrl-C
    does not wait for the whole queue).
    """
    if jobs is not None and jobs < 1:
        raise ValueError(f"jobs must be at least 1, got {jobs}")
    jobs = min(available_cores() if jobs is None else jobs, tasks)
    if jobs <= 1:
        yield None
        return
    context = multiprocessing.get_context("fork" if sys.platform == "linux" else None)
    executor = ProcessPoolExecutor(jobs, mp_context=context, initializer=_start_worker)
    try:
        yield executor
    finally:
        executor.shutdown(wait=True, cancel_futures=True)


def submit_joints(function: Callable[..., Result], tasks: Sequence[tuple],
                  executor: Executor | None) -> Callable[[], list[Result]]:
    """Start ``function(*task)`` for every task in the ``executor``'s workers (in order: longest first balances
    them), or run them here when it is None; the returned function waits for the results, in task order.

    A task holds one joint's data and its own seed, so the result does not depend on where it runs: the same bits
    with one worker or many (core/test_training_fast_paths.py).
    """
    if executor is None:
        results = [function(*task) for task in tasks]
        return lambda: results
    futures = [executor.submit(function, *task) for task in tasks]
    return lambda: [future.result() for future in futures]


def map_joints(function: Callable[..., Result], tasks: Sequence[tuple], executor: Executor | None) -> list[Result]:
    """``function(*task)`` for every task, in order, in the ``executor``'s workers or here (``submit_joints``)."""
    return submit_joints(function, tasks, executor)()
