"""Small dense linear algebra: the per-sample hot path's solve, and BLAS kept to one thread."""
from __future__ import annotations

from contextlib import AbstractContextManager

import numpy as np
from scipy.linalg.lapack import dposv
from threadpoolctl import threadpool_limits


def solve_spd(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``A⁻¹ B`` for symmetric positive-definite ``A`` via a Cholesky solve (LAPACK dposv).

    For the 6×6 and 7×7 systems solved every sample this costs a third of
    ``numpy.linalg.solve``. Raises ``numpy.linalg.LinAlgError`` when A is not positive definite.
    """
    _, solution, info = dposv(a, b)
    if info != 0:
        raise np.linalg.LinAlgError(f"matrix is not positive definite (LAPACK dposv info={info})")
    return solution


def single_threaded_blas() -> AbstractContextManager:
    """A block in which BLAS and OpenMP run one thread.

    For the small dense problems of training, diagnosis and the excitation search (hundreds of
    least-squares fits, ≤ 1000² factorisations): threads gain little there, and on a loaded machine
    OpenBLAS's spinning threads made them 5-100× slower (measured: GMR-GP fit 25 s vs 3.4 s, diagnosis
    QRs 10-100×, excitation products 50×). Results then also do not depend on the core count.
    """
    return threadpool_limits(limits=1)
