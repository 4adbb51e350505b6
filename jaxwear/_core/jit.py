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
with the caller's settings. Where the installed jaxlib does not know an option (jaxlib 0.11
no longer knows `xla_cpu_use_fusion_emitters`: its legacy emitters are gone), the first
compilation says which; the wrapper drops that option alone, keeps the others (O1
included), logs it once and compiles without it from then on.

On the fusion emitters (that jaxlib, or a user's `XLA_FLAGS` that chose them) jaxwear's
programs get `FUSION_REASSOC` instead: XLA:CPU's fast-math switch with every "honor" option
on, which leaves NaN, inf, division and library functions exact and only lets LLVM
reassociate (and contract) floating-point arithmetic. The fusion emitters emit a row sum as
one serial chain of scalar adds, which LLVM may not vectorise without reassociation; the
contact solve's six sums over the nodes (`contact._moments`, one variadic reduction) ran
~5x slower than under the legacy emitters (which vectorise row sums by reassociating them
anyway) and made the boom's 25 h 5x slower (6.0 s against 1.2 s of CPU, docs/performance.md,
"The fusion emitters' row sums"). With it: 1.1-1.3 s. Written-out partial sums, tree sums
over slices, column layouts and matrix products for the same sums were measured on the
fusion emitters without it: 113-275 µs a pass at 360 x 360, against 40 µs reassociated (32
µs legacy): the reassociation has to be LLVM's.

LLVM's O1 (`xla_backend_optimization_level=1`) on top: most of XLA's compile time is
LLVM's optimisation, and O1 compiles a cold rig calibration's programs in 0.88 of the
time at the same run time (the wear loop's profile and Jacobian bitwise the same; a fit's
answer within ~1e-15 relative). Programs that run once per evaluation and in well under a
millisecond (`jit(..., once=True)`: the work estimate's rate bounds, the least-squares
core's damped step and trust-region verdict) compile at O0 (0.4 of their compile
time). With both, a cold `jaxwear calibrate` of the 5-experiment rig study spent 0.83 of
the XLA compile CPU and 0.89 of the CPU time (medians of four pairs;
benchmarks/compile_options.py, docs/performance.md).

XLA:CPU's YNNPACK fusions off (`NO_YNN`): jaxlib 0.10 hands a dot, and a multiply
reduced over an axis that it rewrites into one, to YNNPACK, whose call overhead dominates at
jaxwear's sizes. The contact solve's implicit tangent sums (`contact._residual_at`, per
tangent a (steps, nodes) array summed over the nodes) ran as two YNNPACK fusions that took
17 % of a Jacobian's XLA time (the generator's fatigue study, 48 x 72, 13 columns: 41 of 248
ms a call in XLA's own profile); without them (XLA's own loop emitters for the same sums)
that Jacobian ran in 0.146-0.151 s and 0.25 s of CPU against 0.161-0.179 s and 0.29-0.31 s
(two interleaved pairs each). A forward run holds no such fusion (0.019 s either way).

`JAXWEAR_XLA_DEFAULTS=0` turns every option off; `xla_cpu_use_fusion_emitters` in the
user's own `XLA_FLAGS` turns off the emitters' option (the same switches as
`configure_xla`), `xla_backend_optimization_level` there the level's,
`xla_cpu_enable_fast_math` there the reassociation's, `xla_cpu_experimental_ynn_fusion_type`
there the YNNPACK fusions'. An option this jaxlib does not know is dropped (below); the
YNNPACK one quietly (it is experimental: jaxlibs before and after may not have it).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import re
from collections.abc import Callable, Iterator

import jax

from jaxwear._core import pytree, xla_flags

LEGACY_EMITTERS = {"xla_cpu_use_fusion_emitters": False}
"""XLA:CPU's legacy emitters, asked for on jaxwear's own programs (XLA:CPU options, so
applied on CPU only)."""
FUSION_REASSOC = {"xla_cpu_enable_fast_math": True, "xla_cpu_fast_math_honor_nans": True,
                  "xla_cpu_fast_math_honor_infs": True, "xla_cpu_fast_math_honor_division": True,
                  "xla_cpu_fast_math_honor_functions": True}
"""On the fusion emitters: reassociation (and contraction) of floating-point arithmetic only,
NaN, inf, division and library functions exact (the module's docstring says why)."""
FAST_COMPILE = {"xla_backend_optimization_level": 1}
"""LLVM's O1 for jaxwear's programs (XLA:CPU's default is O2)."""
ONCE_LEVEL = {"xla_backend_optimization_level": 0}
"""The level of `once` programs, wherever the options set a level."""
NO_YNN = {"xla_cpu_experimental_ynn_fusion_type": ""}
"""No fusion handed to YNNPACK (an empty list of its fusion kinds): the module's docstring
says why."""
_QUIET = set(NO_YNN)  # options dropped without a warning where this jaxlib lacks them

_log = logging.getLogger("jaxwear")
_unknown: set[str] = set()  # options the installed jaxlib does not know (each logged once)
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
    elif "xla_cpu_enable_fast_math" not in flags:
        opts.update(FUSION_REASSOC)  # the user chose the fusion emitters
    if "xla_backend_optimization_level" not in flags:
        opts.update(FAST_COMPILE)
    if "xla_cpu_experimental_ynn_fusion_type" not in flags:
        opts.update(NO_YNN)
    return opts or None


def _known(opts: dict | None) -> dict | None:
    """`opts` less the options this jaxlib does not know; where that drops the legacy
    emitters (the program runs on the fusion emitters), `FUSION_REASSOC` instead, unless the
    user's `XLA_FLAGS` set fast math."""
    if not opts:
        return None
    out = {k: v for k, v in opts.items() if k not in _unknown}
    if (opts.get("xla_cpu_use_fusion_emitters") is False
            and "xla_cpu_use_fusion_emitters" in _unknown
            and "xla_cpu_enable_fast_math" not in os.environ.get("XLA_FLAGS", "")):
        out.update({k: v for k, v in FUSION_REASSOC.items()
                    if k not in _unknown and k not in out})
    return out or None


def current_options() -> dict | None:
    """The compiler options jaxwear's next top-level program is compiled with (None: XLA's
    defaults, or the user's `XLA_FLAGS`): the asked-for ones (`options()`, else jaxwear's
    defaults) that this jaxlib knows."""
    return _known(_override[-1] if _override else _default_options())


_UNKNOWN_PATTERNS = (re.compile(r"No such compile option: '([A-Za-z0-9_]+)'"),
                     re.compile(r"While setting option ([A-Za-z0-9_]+)"))


def _unknown_option(message: str, opts: dict) -> str | None:
    """The name of the option of `opts` that a compile error says this jaxlib does not
    know (or cannot set), or None where the message names none of them."""
    for pat in _UNKNOWN_PATTERNS:
        m = pat.search(message)
        if m and m.group(1) in opts:
            return m.group(1)
    return None


def _drop(name: str) -> None:
    """Remember that this jaxlib does not know option `name`; log it once."""
    if name in _unknown:
        return
    _unknown.add(name)
    if name == "xla_cpu_use_fusion_emitters":
        _log.info("this jaxlib (%s) has no legacy emitters (no compile option %s): "
                  "jaxwear's programs compile on the fusion emitters, with reassociation "
                  "allowed (%s)", jax.__version__, name, ", ".join(
                      k for k in FUSION_REASSOC if k not in _unknown))
    else:
        (_log.info if name in _QUIET else _log.warning)(
            "this jaxlib (%s) does not accept the compiler option %s: jaxwear's programs "
            "compile without it", jax.__version__, name)


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
    """`pytree.filter_jit(fun)` that compiles top-level calls with `current_options()`.
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
        """The `pytree.filter_jit` program compiled with `opts` (None: without options)."""
        key = () if not opts else _key(opts)
        f = self._variants.get(key)
        if f is None:
            kw = dict(self._jitkwargs)
            if opts:
                kw["compiler_options"] = dict(opts)
            f = self._variants[key] = pytree.filter_jit(self.fun, **kw)
        return f

    @property
    def _cached(self):
        """The plain program's compilation cache (`_cached._cache_size()`): the
        underlying `jax.jit`."""
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
        # one more try per option this jaxlib may not know, then the error stands
        for _ in range(len(opts) + len(FUSION_REASSOC) + 1):
            try:
                return self.variant(opts)(*args, **kwargs)
            except ValueError as e:
                # traced inside a user's transformation with no traced argument (closed over)
                if "can only be passed to top-level" not in str(e):
                    raise
                return self.variant(None)(*args, **kwargs)
            except Exception as e:  # jaxlib's runtime error: an option it does not know
                if "option" not in str(e):
                    raise
                name = _unknown_option(str(e), opts)
                if name is None and "compile option" not in str(e):
                    raise
                self._variants.pop(_key(opts), None)  # never compiled
                for k in [name] if name else list(opts):  # unnamed: none of them
                    _drop(k)
                opts = self.options()
                if opts is None:
                    return self.variant(None)(*args, **kwargs)
        return self.variant(opts)(*args, **kwargs)

    def lower(self, *args, **kwargs):
        """The top-level program for these arguments traced and lowered with this
        program's options (`pytree.FilterJit.lower`): its `compile()` is the compilation
        the calls with such arguments use after (for compiling ahead in a thread, where
        the tracing and the compilation are wanted at different moments). Where the
        compilation fails (an option this jaxlib does not know) a call compiles instead."""
        return self.variant(self.options()).lower(*args, **kwargs)

    def __get__(self, obj, objtype=None):
        # as a method decorator: bind like a function
        return self if obj is None else functools.partial(self, obj)


def jit(fun: Callable | None = None, **jitkwargs):
    """jaxwear's jit: `Jit(fun)`; usable as `@jit` or `@jit(donate=...)`."""
    if fun is None:
        return lambda f: Jit(f, **jitkwargs)
    return Jit(fun, **jitkwargs)
