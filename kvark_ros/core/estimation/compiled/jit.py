"""``jit``, the decorator of every kernel of ``core.estimation.compiled``, and the rule that keeps numba's cache exact.

numba's on-disk cache (``cache=True``: ``__pycache__`` next to the kernel's file, or ``NUMBA_CACHE_DIR``) is keyed on
the kernel's own file only: a kernel that calls a kernel of another file, or reads a layout of ``layouts.py`` (whose
members it freezes into its machine code as constants), would stay stale in the cache when only that other file
changed. So every kernel file names the files its kernels read in ``PINS``, ``{file name: sha256 of its content}``:
changing a pinned file changes the pinning file's content, and numba recompiles both.
``test/core/test_compiled_step_matches_reference.py`` fails, printing the new digests, until the pins are updated, and
checks that no kernel reads a global of another file that is not pinned.
"""
from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Callable

import numba

HERE = Path(__file__).resolve().parent


def jit(function: Callable) -> Callable:
    """``numba.njit`` with numpy's IEEE semantics (inf/nan, no ZeroDivisionError) and numba's on-disk cache.

    Where no cache directory is writable (no ``NUMBA_CACHE_DIR``, a read-only install, no writable home) numba
    refuses ``cache=True`` when decorating; the kernels then compile at every start instead (~13 s)."""
    try:
        return numba.njit(cache=True, error_model="numpy")(function)
    except RuntimeError:                            # numba: "cannot cache function …: no locator available"
        return numba.njit(error_model="numpy")(function)


def digest(name: str) -> str:
    """sha256 of the kernel file ``name`` of this package (a ``PINS`` value)."""
    return hashlib.sha256((HERE / name).read_bytes()).hexdigest()
