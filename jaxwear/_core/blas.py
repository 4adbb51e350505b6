"""The host BLAS's thread pool, held to one thread by the command line (`limit`).

Why: the host's linear algebra is small (the fits' SVDs of a (rows ~3000, columns ≤ 60)
whitened Jacobian, the shape's smoothers, the law screen's pseudo-inverses), and it runs
beside XLA's own threads (the wear loop's runs and the background compilations of
`diagnose --shape`). OpenBLAS's second thread then waits for a core by spinning: measured
on a 2-core machine under load, one SVD of a 3030 x 52 matrix took 150 ms of CPU with two
threads and 3.4 ms with one; `diagnose --shape` on the generator's `fatigue` study spent
~54 s (py-spy samples) in `np.linalg.svd`. One thread does the same work without the wait,
and its results no longer depend on how many cores the machine has (a threaded BLAS splits
its sums by the thread count: the refits' trajectories moved in the last bits with it).

The command line's choice, as XLA's flags are (`xla_flags`): the library leaves a user's
process as it finds it. A user's own `OPENBLAS_NUM_THREADS` / `OMP_NUM_THREADS` is kept.
"""

from __future__ import annotations

import ctypes
import os

ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")
# the setters of the OpenBLAS builds numpy and scipy bundle (scipy-openblas, 64- and
# 32-bit integers) and of a plain OpenBLAS
SETTERS = ("scipy_openblas_set_num_threads64_", "scipy_openblas_set_num_threads",
           "openblas_set_num_threads64_", "openblas_set_num_threads")


def _loaded_openblas() -> list[str]:
    """Paths of the OpenBLAS libraries this process has loaded (Linux: /proc/self/maps;
    elsewhere none are found and nothing is changed)."""
    try:
        with open("/proc/self/maps") as f:
            paths = {line.split()[-1] for line in f if "openblas" in line.lower()}
    except OSError:
        return []
    return sorted(p for p in paths if p.startswith("/"))


def limit(threads: int = 1) -> int:
    """Hold the host BLAS to `threads` threads, unless the user's environment chose
    (`ENV`): the libraries already loaded by their setter, those loaded later (scipy's, on
    its first use) by the environment variable they read when they load. Returns how many
    loaded libraries were set (0 where the user chose, or none was found)."""
    if any(os.environ.get(k) for k in ENV):
        return 0
    os.environ["OPENBLAS_NUM_THREADS"] = str(threads)
    done = 0
    for path in _loaded_openblas():
        try:
            lib = ctypes.CDLL(path, mode=getattr(os, "RTLD_NOLOAD", 0) | ctypes.RTLD_GLOBAL)
        except OSError:
            continue
        for name in SETTERS:
            fn = getattr(lib, name, None)
            if fn is not None:
                fn.argtypes = [ctypes.c_int]
                fn.restype = None
                fn(int(threads))
                done += 1
                break
    return done
