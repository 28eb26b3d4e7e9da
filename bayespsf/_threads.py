"""One BLAS thread for the small dense algebra of one molecule.

A 6-parameter fit calls BLAS on vectors of length 6 (L-BFGS-B's updates, 6x6 solves). OpenBLAS
then wakes its thread pool for no gain; on a machine whose cores are busy (a batch run, a
shared server) the handoffs made one maximum-likelihood fit 2-20x slower (5 ms idle, 9-100 ms
with both cores loaded; measured with scipy 1.18 / OpenBLAS 0.3.34 on 2 cores). Limiting BLAS
to one thread while a molecule is fitted or sampled removes that cost; it is restored after.
"""

from __future__ import annotations

import functools
import threading

from threadpoolctl import ThreadpoolController


@functools.cache
def _controller() -> ThreadpoolController:
    return ThreadpoolController()  # inspects the loaded libraries once (~1 ms)


def single_blas_thread():
    """Context manager: BLAS limited to one thread inside it (~20 us to enter and leave)."""
    return _controller().limit(limits=1, user_api="blas")


def one_blas_thread(function):
    """Decorator: ``function`` runs with BLAS limited to one thread when called from the main
    thread. The limit is process-wide, so calls from other threads (a threaded Dask worker)
    leave it alone rather than race each other's enter and exit."""

    @functools.wraps(function)
    def limited(*args, **kwargs):
        if threading.current_thread() is not threading.main_thread():
            return function(*args, **kwargs)
        with single_blas_thread():
            return function(*args, **kwargs)

    return limited
