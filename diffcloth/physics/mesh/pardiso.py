"""Intel MKL PARDISO (a supernodal sparse direct solver) through ctypes, for `linsolve`'s host
factorizations where the `mkl` wheel is installed (`pip install "diffcloth[fast]"`, x86_64).

On the 2,846-vertex drape's Newton systems (5,448 unknowns, float32, one core) a numeric
factorization takes ~11 ms and a solve ~0.5 ms, against SciPy SuperLU's ~42 ms and ~1.0 ms on
the same matrices in the same ordering: SuperLU is not supernodal, and it factors both
triangles of a symmetric matrix. The matrix type is real symmetric indefinite (Bunch-Kaufman
pivoting with pivot perturbation), so any symmetric system factors, as it did with SuperLU's
symmetric mode.

One `Analysis` is one sparsity pattern (the upper triangle, CSR, zero-based), ordered and
analysed once (METIS nested dissection), with up to `slots` numeric factorizations of that
pattern alive at a time (PARDISO's `maxfct` / `mnum`). Calls on one analysis hold its lock.

MKL is loaded on first use, with its sequential threading layer unless $MKL_THREADING_LAYER
says otherwise: one thread gives the same factors on every run (MKL's OpenMP factorization
rounds differently from run to run, so a Newton solve took another path each time), and no
OpenMP threads spin against XLA's on the same cores (where a threaded layer is asked for,
`KMP_BLOCKTIME` defaults to 0). In a process forked after MKL was loaded, `available` is False.
"""

from __future__ import annotations

import ctypes
import glob
import os
import site
import sys
import threading
import weakref
from ctypes.util import find_library

import numpy as np

__all__ = ["Analysis", "available"]

_LIB: list = [None, None]  # [the pardiso function, or False where MKL is missing; pid]
_LIB_LOCK = threading.Lock()

#: PARDISO's error codes (its `error` argument)
_ERRORS = {-1: "input inconsistent", -2: "not enough memory", -3: "reordering problem",
           -4: "zero pivot", -5: "unclassified internal error", -6: "reordering failed",
           -7: "diagonal matrix is singular", -8: "32-bit integer overflow",
           -9: "not enough memory for out-of-core", -10: "cannot open out-of-core files",
           -11: "read/write problem with out-of-core files"}  # fmt: skip


def _candidates() -> list[str]:
    """Paths or names of MKL's single dynamic library: $DIFFCLOTH_MKL_RT, the loader's search
    path, then the `mkl` wheel's lib/ under this interpreter's prefix or the user site."""
    named = [os.environ.get("DIFFCLOTH_MKL_RT"), find_library("mkl_rt"), find_library("mkl_rt.2")]
    found: list[str] = []
    for base in (sys.prefix, site.USER_BASE or ""):  # lib/ (Linux), Library/bin (Windows)
        found += sorted(
            glob.glob(f"{base}/lib/*mkl_rt*") + glob.glob(f"{base}/Library/bin/*mkl_rt*")
        )
    return [p for p in named if p] + [
        p for p in found if ".so" in p or p.endswith((".dll", ".dylib"))
    ]


def _load():
    with _LIB_LOCK:
        if _LIB[0] is None:
            os.environ.setdefault("MKL_THREADING_LAYER", "SEQUENTIAL")
            os.environ.setdefault("KMP_BLOCKTIME", "0")
            fn = False
            for path in _candidates():
                try:
                    fn = ctypes.CDLL(path).pardiso
                    break
                except (OSError, AttributeError):
                    continue
            if fn:
                fn.restype = None
            _LIB[0], _LIB[1] = fn, os.getpid()
        return _LIB[0]


def available() -> bool:
    """True where MKL's PARDISO loads (and this process is the one that loaded it); whether it
    is used is `linsolve`'s choice ($DIFFCLOTH_SPARSE_SOLVER). Shapes: none."""
    fn = _load()
    return bool(fn) and _LIB[1] == os.getpid()


def _i32(v: int):
    return ctypes.byref(ctypes.c_int32(v))


def _release_all(fn, pt, slots, n, iparm, dtype) -> None:
    """PARDISO phase -1: free every factorization and the analysis of handle pt."""
    if _LIB[1] != os.getpid():  # a forked child: the parent's memory, not ours to free
        return
    p = ctypes.c_void_p
    err = ctypes.c_int32(0)
    dummy = np.zeros(max(n, 1), dtype)
    idx = np.zeros(max(n, 1) + 1, np.int32)
    fn(pt.ctypes.data_as(p), _i32(slots), _i32(1), _i32(-2), _i32(-1), _i32(n),
       dummy.ctypes.data_as(p), idx.ctypes.data_as(p), idx.ctypes.data_as(p), p(), _i32(1),
       iparm.ctypes.data_as(p), _i32(0), dummy.ctypes.data_as(p), dummy.ctypes.data_as(p),
       ctypes.byref(err))  # fmt: skip


class Analysis:
    """One analysed sparsity pattern: `factor` numeric factorizations into its slots, `solve`
    with one, `release` a slot. indptr (n + 1,), indices (nnz,): the upper triangle (diagonal
    included) of a symmetric n x n matrix in CSR, zero-based, sorted. single: factor and solve
    in float32 (data and right-hand sides float32) instead of float64."""

    def __init__(self, indptr: np.ndarray, indices: np.ndarray, n: int, single: bool,
                 slots: int = 1):  # fmt: skip
        self._fn = _load()
        if not self._fn:
            raise RuntimeError("MKL's PARDISO is not available (pip install 'diffcloth[fast]')")
        self.n, self.slots, self.single = int(n), int(slots), bool(single)
        self.dtype = np.float32 if single else np.float64
        self.indptr = np.ascontiguousarray(indptr, np.int32)
        self.indices = np.ascontiguousarray(indices, np.int32)
        self._pt = np.zeros(64, np.int64)  # PARDISO's opaque handle
        self._iparm = np.zeros(64, np.int32)
        ip = self._iparm
        ip[0] = 1  # these settings, not the defaults
        ip[1] = 2  # METIS nested dissection
        ip[9] = 6 if single else 8  # pivot perturbation 10^-k
        ip[10] = 0  # no scaling
        ip[12] = 0  # no weighted matching
        ip[20] = 1  # Bunch-Kaufman pivoting
        ip[23] = 0  # the classic (not two-level) factorization: small systems
        ip[27] = 1 if single else 0
        ip[34] = 1  # zero-based indices
        self._free = list(range(self.slots, 0, -1))  # mnum values not in use
        self._values: dict[int, np.ndarray] = {}  # slot -> its matrix (refinement reads it)
        self._lock = threading.Lock()
        self._data = np.zeros(len(self.indices), self.dtype)  # analysis reads the pattern only
        err = self._call(11, 1, self._data, np.zeros(self.n, self.dtype))
        # PARDISO's memory is released with the analysis (phase -1), or at exit
        weakref.finalize(self, _release_all, self._fn, self._pt, self.slots, self.n,
                         self._iparm, self.dtype)  # fmt: skip
        if err:
            raise RuntimeError(f"PARDISO analysis failed: {_ERRORS.get(err, err)}")

    def _call(self, phase: int, mnum: int, data: np.ndarray, rhs: np.ndarray,
              out: np.ndarray | None = None) -> int:  # fmt: skip
        err = ctypes.c_int32(0)
        out = np.zeros_like(rhs) if out is None else out
        p = ctypes.c_void_p
        self._fn(self._pt.ctypes.data_as(p), _i32(self.slots), _i32(mnum), _i32(-2), _i32(phase),
                 _i32(self.n), data.ctypes.data_as(p), self.indptr.ctypes.data_as(p),
                 self.indices.ctypes.data_as(p), p(), _i32(1), self._iparm.ctypes.data_as(p),
                 _i32(0), rhs.ctypes.data_as(p), out.ctypes.data_as(p), ctypes.byref(err))  # fmt: skip
        return int(err.value)

    def factor(self, data: np.ndarray) -> int | None:
        """Numeric factorization of the matrix with these values (nnz,); returns its slot, or
        None where PARDISO fails. A slot stays in use until `release`."""
        data = np.ascontiguousarray(data, self.dtype)
        with self._lock:
            if not self._free:
                raise RuntimeError(f"all {self.slots} factorization slots of this pattern in use")
            slot = self._free.pop()
            err = self._call(22, slot, data, np.zeros(self.n, self.dtype))
            if err:
                self._free.append(slot)
                return None
            self._values[slot] = data
        return slot

    def solve(self, slot: int, rhs: np.ndarray) -> np.ndarray:
        """x with A x = rhs (n,) for the factorization in `slot`."""
        rhs = np.ascontiguousarray(rhs, self.dtype)
        out = np.zeros_like(rhs)
        with self._lock:
            err = self._call(33, slot, self._values[slot], rhs, out)
        if err:
            out[:] = np.nan
        return out

    def release(self, slot: int) -> None:
        """Free a slot for the next `factor` (its memory is reused, not returned)."""
        with self._lock:
            if slot not in self._free:
                self._free.append(slot)
                self._values.pop(slot, None)
