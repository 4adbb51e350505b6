"""XLA:CPU compiler options, opted in to before JAX starts its CPU backend: by the command
line (`cli.main`), by a library user with `jaxwear.configure_xla()`, and by the tests.

Compilation is about half of a cold answer and most of the test suite's time: one wear
loop's program runs in ~0.05 s and compiles in 2-4 s. XLA:CPU's newer MLIR fusion emitters
(on by default since jaxlib 0.6) compile these programs about 1.7x slower than its legacy
elemental emitters (measured, 2 cores, 64 x 72 rig, 10⁴ revolutions: adaptive loop's
Jacobian 3.3-3.7 s -> 1.6-2.0 s, forward 2.6-3.3 s -> 1.4-1.9 s; a full diagnosis test 86 s
-> 57 s, its compilations 58 s -> 30 s), and run the wear loop slower too (the contact
solve's variadic reduction ~2.5x: the boom's 25 h at 360 x 360 2-3x; docs/performance.md).
So the legacy emitters are asked for, unless the user's own `XLA_FLAGS` say otherwise.

jaxwear's own programs get them without this switch (`jaxwear._core.jit`: per-program
compiler options); the switch is for everything else the process compiles (the command
line's and the tests' own small programs).

Only for the jaxlib versions where the flag was checked to exist (an unknown flag aborts
the process when XLA starts): 0.6 up to 0.10. `JAXWEAR_XLA_DEFAULTS=0` turns this off.
"""

from __future__ import annotations

import os

FLAG = "--xla_cpu_use_fusion_emitters=false"
CHECKED = ((0, 6), (0, 10))  # jaxlib (major, minor), inclusive


def _jaxlib_version() -> tuple[int, int] | None:
    from importlib.metadata import PackageNotFoundError, version

    try:
        parts = version("jaxlib").split(".")
        return int(parts[0]), int(parts[1])
    except (PackageNotFoundError, ValueError, IndexError):
        return None


_APPLIED: list[bool] = []  # `apply` appended FLAG in this process


def applied() -> bool:
    """Whether `FLAG` in `XLA_FLAGS` is this process's `apply` (not the user's choice)."""
    return bool(_APPLIED) and FLAG in os.environ.get("XLA_FLAGS", "")


def apply() -> bool:
    """Append `FLAG` to `XLA_FLAGS`: XLA:CPU's legacy emitters for every program of the
    process (jaxwear's own programs ask for them per program without this; this covers the
    rest: a user's own `jax.jit` around jaxwear's functions, for instance).
    Effective only before JAX's CPU backend starts (the first computation). Returns whether
    it did: not where `JAXWEAR_XLA_DEFAULTS=0`, the user's `XLA_FLAGS` already choose, or the
    installed jaxlib was not checked to know the flag."""
    if os.environ.get("JAXWEAR_XLA_DEFAULTS", "1") == "0":
        return False
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_use_fusion_emitters" in flags:
        return False  # the user's choice
    v = _jaxlib_version()
    if v is None or not (CHECKED[0] <= v <= CHECKED[1]):
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {FLAG}".strip()
    _APPLIED.append(True)
    return True
