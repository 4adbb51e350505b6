"""The command line holds the host BLAS to one thread (`jaxwear._core.blas`), unless the
user's environment chose; checked in fresh processes (a limit is process-wide)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

# numpy's bundled OpenBLAS, asked by its own getter after the CLI's entry has run
PROBE = """
import ctypes, json, os
import numpy as np
from jaxwear._core import blas
before = os.environ.get("OPENBLAS_NUM_THREADS")
n = blas.limit(1)
counts = []
for path in blas._loaded_openblas():
    lib = ctypes.CDLL(path, mode=os.RTLD_NOLOAD)
    for name in ("scipy_openblas_get_num_threads64_", "scipy_openblas_get_num_threads",
                 "openblas_get_num_threads64_", "openblas_get_num_threads"):
        f = getattr(lib, name, None)
        if f is not None:
            f.restype = ctypes.c_int
            counts.append(f())
            break
print(json.dumps({"set": n, "counts": counts, "before": before,
                  "after": os.environ.get("OPENBLAS_NUM_THREADS")}))
"""


def _run(env_extra: dict) -> dict:
    import json

    env = {k: v for k, v in os.environ.items()
           if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")}
    env.update(env_extra)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/self/maps")
def test_the_loaded_blas_is_held_to_one_thread_and_later_ones_by_the_environment():
    r = _run({})
    if not r["counts"]:
        pytest.skip("numpy is not linked to an OpenBLAS here")
    assert r["set"] >= 1 and r["counts"] == [1] * len(r["counts"]), r
    assert r["before"] is None and r["after"] == "1", r


def test_a_users_own_thread_count_is_kept():
    r = _run({"OPENBLAS_NUM_THREADS": "2"})
    assert r["set"] == 0 and r["after"] == "2", r
    r = _run({"OMP_NUM_THREADS": "3"})
    assert r["set"] == 0 and r["after"] is None, r
