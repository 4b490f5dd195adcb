"""The dense solve's Cholesky factorisation on several threads, robust on a busy machine.

OpenBLAS's threaded ``dpotrf`` synchronises its threads many times per panel by spinning. On a
machine whose cores are busy with other processes a synchronisation waits for a thread the
kernel has descheduled: factoring the igea mesh's 2,152 x 2,152 kernel matrix took 2.8-2.9 s on
2 threads beside two CPU-busy processes instead of 0.05 s idle (0.08-0.14 s on one thread
beside them), and the worker threads spin between calls, taking time from everything else.

So on more than one thread the factorisation here is blocked (right-looking, :data:`PANEL`
columns per step, in place) and its parallel parts run on Python threads, each calling the
one-threaded BLAS on its own share: the rows of the panel's triangular solve (``dtrsm``), and
column ranges of equal area of the trailing update (``dsyrk`` on the diagonal, ``dgemm`` below).
The BLAS routines are LAPACK's own, called through the raw function pointers that
``scipy.linalg.cython_blas`` / ``cython_lapack`` export (ctypes releases the interpreter lock
during a call, and passes the leading dimension, so the blocks are views of the one matrix, not
copies). Measured on the development machine, 2 threads: 0.044 s idle on 2,152 points (threaded
``dpotrf`` 0.045 s, one thread 0.078 s), 0.078 s on 2,705 (0.088 s), 0.26 s on 4,136 (0.27 s);
beside two busy processes 0.08-0.13 s on 2,152 (one thread 0.08-0.16 s). On one thread it is
one ``dpotrf``, and so is a matrix smaller than :data:`MIN_THREADED`.
"""

from __future__ import annotations

import ctypes
import functools
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from itertools import pairwise

import numpy as np
from scipy.linalg import LinAlgError, lapack

from splatdeform.blas import blas_threads

#: Columns per step of the blocked factorisation (256 and 512 measured within 3%).
PANEL = 256
#: Smallest matrix factored on several threads: below it one ``dpotrf`` on one thread (30 ms
#: at 1,536; two threads saved 2-3 ms idle at 1,100, and cost up to 3x beside busy processes,
#: where every join waits for a descheduled thread).
MIN_THREADED = 1536


def factor_lower(a: np.ndarray, threads: int = 1) -> np.ndarray:
    """Cholesky factor L (lower triangle) of the symmetric positive definite ``a`` (n, n)
    float64, Fortran-ordered, of which only the lower triangle is read; factored in place and
    returned (the upper triangle is left as it was).

    threads: threads of the factorisation. Raises ``scipy.linalg.LinAlgError`` when ``a`` is
    not positive definite.
    """
    if a.dtype != np.float64 or not a.flags.f_contiguous or a.ndim != 2 \
            or a.shape[0] != a.shape[1]:
        raise ValueError("a: expected a square Fortran-ordered float64 array")
    n = a.shape[0]
    if threads <= 1 or n < max(MIN_THREADED, 2 * PANEL):
        with blas_threads(1):
            low, info = lapack.dpotrf(a, lower=1, overwrite_a=1, clean=0)
        _check(info)
        return low
    with blas_threads(1), ThreadPoolExecutor(threads) as pool:
        _blocked(a, threads, pool)
    return a


def solve_lower(low: np.ndarray, b: np.ndarray) -> np.ndarray:
    """x (n, k) with L L^T x = b, L the lower triangle of ``low`` (:func:`factor_lower`),
    b (n, k) float64 (one thread: k is small)."""
    with blas_threads(1):
        x, info = lapack.dpotrs(low, b, lower=1)
    if info:
        raise ValueError(f"dpotrs: illegal argument {-info}")
    return x


def _check(info: int) -> None:
    if info > 0:
        raise LinAlgError(f"the matrix is not positive definite (leading minor {info})")
    if info < 0:
        raise ValueError(f"dpotrf: illegal argument {-info}")


def _blocked(a: np.ndarray, threads: int, pool: ThreadPoolExecutor) -> None:
    """Right-looking blocked Cholesky of ``a`` in place, the parallel parts on ``pool``."""
    f = _routines()
    n = ld = a.shape[0]
    base = a.ctypes.data

    def at(row: int, col: int) -> ctypes.c_void_p:  # address of a[row, col]
        return ctypes.c_void_p(base + 8 * (row + col * ld))

    def run(tasks: list[Callable[[], None]]) -> None:
        for done in [pool.submit(task) for task in tasks]:
            done.result()

    for s in range(0, n, PANEL):
        e = min(s + PANEL, n)
        b = e - s
        info = ctypes.c_int(0)
        f.dpotrf(_CH[b"L"], _int(b), at(s, s), _int(ld), ctypes.byref(info))
        _check(info.value + (s if info.value > 0 else 0))
        rest = n - e
        if not rest:
            break
        rows = [e + (k * rest) // threads for k in range(threads + 1)]  # the panel's rows
        run([functools.partial(f.dtrsm, _CH[b"R"], _CH[b"L"], _CH[b"T"], _CH[b"N"],
                               _int(r1 - r0), _int(b), _ONE, at(s, s), _int(ld),
                               at(r0, s), _int(ld))
             for r0, r1 in pairwise(rows) if r1 > r0])
        # trailing columns e..n in ranges of equal area of the lower triangle
        cols = [e + int(round(rest * (1.0 - np.sqrt(1.0 - k / threads))))
                for k in range(threads + 1)]
        tasks = []
        for c0, c1 in pairwise(cols):
            if c1 <= c0:
                continue
            tasks.append(functools.partial(
                f.dsyrk, _CH[b"L"], _CH[b"N"], _int(c1 - c0), _int(b), _MINUS_ONE,
                at(c0, s), _int(ld), _ONE, at(c0, c0), _int(ld)))
            if c1 < n:
                tasks.append(functools.partial(
                    f.dgemm, _CH[b"N"], _CH[b"T"], _int(n - c1), _int(c1 - c0), _int(b),
                    _MINUS_ONE, at(c1, s), _int(ld), at(c0, s), _int(ld), _ONE, at(c1, c0),
                    _int(ld)))
        run(tasks)


_CH = {c: ctypes.c_char_p(c) for c in (b"L", b"R", b"N", b"T")}
_ONE = ctypes.byref(ctypes.c_double(1.0))
_MINUS_ONE = ctypes.byref(ctypes.c_double(-1.0))


def _int(value: int):
    return ctypes.byref(ctypes.c_int(int(value)))


class _Routines:
    """ctypes callables of LAPACK's dpotrf and BLAS's dtrsm, dsyrk, dgemm (every argument by
    reference, Fortran order, 32-bit integers: scipy's LP64 OpenBLAS)."""

    def __init__(self) -> None:
        from scipy.linalg import cython_blas, cython_lapack

        self.dpotrf = _pointer(cython_lapack, "dpotrf", 5)
        self.dtrsm = _pointer(cython_blas, "dtrsm", 11)
        self.dsyrk = _pointer(cython_blas, "dsyrk", 10)
        self.dgemm = _pointer(cython_blas, "dgemm", 13)


@functools.cache
def _routines() -> _Routines:
    return _Routines()


def _pointer(module, name: str, nargs: int):
    """The C function ``name`` exported by a scipy Cython module, as a ctypes callable that
    releases the interpreter lock while it runs."""
    capsule = module.__pyx_capi__[name]
    get_name = ctypes.pythonapi.PyCapsule_GetName
    get_name.restype, get_name.argtypes = ctypes.c_char_p, [ctypes.py_object]
    get_pointer = ctypes.pythonapi.PyCapsule_GetPointer
    get_pointer.restype = ctypes.c_void_p
    get_pointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
    address = get_pointer(capsule, get_name(capsule))
    return ctypes.CFUNCTYPE(None, *([ctypes.c_void_p] * nargs))(address)
