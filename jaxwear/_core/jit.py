"""jaxwear's own compiled programs: one wrapper, `jit`, for every program the package
compiles (the wear loop, the fits' evaluations, the sweeps), so that XLA compiler options
apply to jaxwear's programs and to nothing else in the user's process.

Why: XLA:CPU's MLIR fusion emitters (its default since jaxlib 0.6) compile the wear loop
1.5-2x slower than its legacy elemental emitters and run it slower too (the boom's 25 h
duty cycle at 360 x 360: 3.2x slower, a rig run 1.4x; docs/performance.md). The process-wide
`XLA_FLAGS` switch (`jaxwear.configure_xla`) is the user's to set, so the legacy emitters
are asked for per program (`jax.jit(..., compiler_options=...)`), which leaves every other
program of the process on the user's settings.

Per-program options apply to top-level programs only: JAX refuses them on a jit traced
inside another transformation (`jax.grad`, `jax.vmap`, a user's `jax.jit`). There the
wrapper calls the same function without options, and the program it is part of is compiled
with the caller's settings. Where the installed jaxlib does not know an option, the first
compilation says so, the wrapper logs it once and runs without options from then on.

LLVM's O1 (`xla_backend_optimization_level=1`) on top: most of XLA's compile time is
LLVM's optimisation, and O1 compiles a cold rig calibration's programs in 0.88 of the
time at the same run time (the wear loop's profile and Jacobian bitwise the same; a fit's
answer within ~1e-15 relative). Programs that run once per evaluation and in well under a
millisecond (`jit(..., once=True)`: the work estimate's rate bounds, the least-squares
core's damped step and trust-region verdict) compile at O0 (0.4 of their compile
time). With both, a cold `jaxwear calibrate` of the 5-experiment rig study spent 0.83 of
the XLA compile CPU and 0.89 of the CPU time (medians of four pairs;
benchmarks/compile_options.py, docs/performance.md).

`JAXWEAR_XLA_DEFAULTS=0` turns every option off; `xla_cpu_use_fusion_emitters` in the
user's own `XLA_FLAGS` turns off the emitters' option (the same switches as
`configure_xla`), `xla_backend_optimization_level` there the level's.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
from collections.abc import Callable, Iterator

import equinox as eqx
import jax

from jaxwear._core import xla_flags

LEGACY_EMITTERS = {"xla_cpu_use_fusion_emitters": False}
"""XLA:CPU's legacy emitters, asked for on jaxwear's own programs (XLA:CPU options, so
applied on CPU only)."""
FAST_COMPILE = {"xla_backend_optimization_level": 1}
"""LLVM's O1 for jaxwear's programs (XLA:CPU's default is O2)."""
ONCE_LEVEL = {"xla_backend_optimization_level": 0}
"""The level of `once` programs, wherever the options set a level."""

_log = logging.getLogger("jaxwear")
_rejected: set[tuple] = set()  # option sets the installed jaxlib refused (logged once)
_override: list[dict | None] = []  # `options()` stack (benchmarks, tests)


def _default_options() -> dict | None:
    if os.environ.get("JAXWEAR_XLA_DEFAULTS", "1") == "0":
        return None
    if jax.default_backend() != "cpu":
        return None
    flags = os.environ.get("XLA_FLAGS", "")
    opts = {}
    # the user's own choice, process-wide, is kept (not the flag `configure_xla` set: the
    # same choice as ours)
    if "xla_cpu_use_fusion_emitters" not in flags or xla_flags.applied():
        opts.update(LEGACY_EMITTERS)
    if "xla_backend_optimization_level" not in flags:
        opts.update(FAST_COMPILE)
    return opts or None


def current_options() -> dict | None:
    """The compiler options jaxwear's next top-level program is compiled with (None: XLA's
    defaults, or the user's `XLA_FLAGS`)."""
    opts = _override[-1] if _override else _default_options()
    if not opts or _key(opts) in _rejected:
        return None
    return opts


@contextlib.contextmanager
def options(opts: dict | None) -> Iterator[None]:
    """Compile jaxwear's programs with `opts` (None: no per-program options) inside the
    block: for benchmarks and tests that compare emitter families in one process."""
    _override.append(opts)
    try:
        yield
    finally:
        _override.pop()


def _key(opts: dict) -> tuple:
    return tuple(sorted(opts.items()))


def _traced(args, kwargs) -> bool:
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves((args, kwargs)))


class Jit:
    """`eqx.filter_jit(fun)` that compiles top-level calls with `current_options()`.
    Arrays are traced, everything else is static (as `eqx.filter_jit`). `once`: a program
    run once per evaluation in well under a millisecond, compiled at `ONCE_LEVEL` wherever
    the options set an optimisation level."""

    def __init__(self, fun: Callable, *, once: bool = False, **jitkwargs):
        self.fun = fun
        self.once = once
        self._jitkwargs = jitkwargs
        self._variants: dict[tuple, Callable] = {}
        functools.update_wrapper(self, fun)

    def variant(self, opts: dict | None) -> Callable:
        """The `eqx.filter_jit` program compiled with `opts` (None: without options)."""
        key = () if not opts else _key(opts)
        f = self._variants.get(key)
        if f is None:
            kw = dict(self._jitkwargs)
            if opts:
                kw["compiler_options"] = dict(opts)
            f = self._variants[key] = eqx.filter_jit(self.fun, **kw)
        return f

    @property
    def _cached(self):
        """The plain program's compilation cache (`_cached._cache_size()`), as
        `eqx.filter_jit`'s."""
        return self.variant(self.options())._cached

    def options(self) -> dict | None:
        """The options this program's next top-level call is compiled with."""
        opts = current_options()
        if opts and self.once and "xla_backend_optimization_level" in opts:
            opts = {**opts, **ONCE_LEVEL}
        return opts

    def __call__(self, *args, **kwargs):
        opts = self.options()
        if opts is None or _traced(args, kwargs):
            return self.variant(None)(*args, **kwargs)
        try:
            return self.variant(opts)(*args, **kwargs)
        except ValueError as e:
            # traced inside a user's transformation with no traced argument (closed over)
            if "can only be passed to top-level" not in str(e):
                raise
            return self.variant(None)(*args, **kwargs)
        except Exception as e:  # jaxlib's runtime error: an option it does not know
            if "compile option" not in str(e):
                raise
            _rejected.add(_key(opts))
            _log.warning("this jaxlib (%s) does not accept the compiler options %s (%s): "
                         "jaxwear's programs compile with XLA's defaults",
                         jax.__version__, opts, str(e).splitlines()[0])
            return self.variant(None)(*args, **kwargs)

    def __get__(self, obj, objtype=None):
        # as a method decorator: bind like a function
        return self if obj is None else functools.partial(self, obj)


def jit(fun: Callable | None = None, **jitkwargs):
    """jaxwear's jit: `Jit(fun)`; usable as `@jit` or `@jit(donate=...)`."""
    if fun is None:
        return lambda f: Jit(f, **jitkwargs)
    return Jit(fun, **jitkwargs)
