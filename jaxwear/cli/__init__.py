"""Command line: `jaxwear simulate|calibrate|diagnose|synth|sweep|sensitivity|predict|design`
(design.md §7).

Exit codes: 0 done, 2 bad input (one line naming the file, key, line or option), 1 anything
else. Set JAXWEAR_DEBUG=1 to see tracebacks. Every verb takes the same path (`_pipeline`):
parse, load the study, check the outputs, estimate the work, run.
"""

from __future__ import annotations

import functools
import os
import sys
from pathlib import Path

import jax

from jaxwear._core.blas import limit as limit_blas
from jaxwear._core.errors import (
    FitError,
    InputError,
    ModelFailure,
    NoSpaceError,
    TrialFailed,
    WornThroughError,
)
from jaxwear._core.interrupt import (
    EXIT_CODE,
    MESSAGE,
    end_process,
    interrupted,
    launched_as_cli,
    release,
    restore,
    shutting_down,
)
from jaxwear._core.io import FULL
from jaxwear._core.xla_flags import apply as configure_xla
from jaxwear._study.effect_files import effect_file_frame
from jaxwear.cli._parser import Parser, join_negative_values, value_options

# verb name: (module, class), in the order `--help` lists them. A verb's module is imported
# when it is named: the diagnose and design packages (scipy.stats with them) cost ~0.6 s of
# every start-up otherwise.
VERBS = {"simulate": ("jaxwear.cli.simulate", "Simulate"),
         "calibrate": ("jaxwear.cli.calibrate", "Calibrate"),
         "diagnose": ("jaxwear.cli.diagnose", "Diagnose"),
         "synth": ("jaxwear.cli.synth", "Synth"),
         "sweep": ("jaxwear.cli.sweep", "Sweep"),
         "sensitivity": ("jaxwear.cli.sensitivity", "Sensitivity"),
         "predict": ("jaxwear.cli.predict", "Predict"),
         "design": ("jaxwear.cli.design", "Design")}


def _verbs(only: str | None = None):
    """The verbs (all, or the one named `only`)."""
    import importlib

    names = [only] if only in VERBS else list(VERBS)
    return [getattr(importlib.import_module(VERBS[n][0]), VERBS[n][1])() for n in names]


def _enable_cache():
    # A persistent compilation cache makes the second start of the CLI fast. Opt out with
    # JAXWEAR_NO_CACHE=1. This is the CLI's choice; the library never touches it.
    if os.environ.get("JAXWEAR_NO_CACHE"):
        return

    cache = os.environ.get("JAXWEAR_CACHE_DIR",
                           str(Path.home() / ".cache" / "jaxwear" / "jax-compilation"))
    try:
        jax.config.update("jax_compilation_cache_dir", cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    except Exception:  # an unwritable home is no reason to fail
        pass


def build_parser(only: str | None = None) -> Parser:
    """The command line's parser: every verb, or only the verb named `only` (the one a
    command line asks for: the others' modules are not imported)."""
    ap = Parser(prog="jaxwear", description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="verb_name", required=True, metavar="VERB")
    for verb in _verbs(only):
        verb.add_to(sub)
    return ap


def main(argv=None) -> int:
    # the command line's own process opts in to XLA:CPU's faster-compiling emitters (the
    # library leaves XLA's settings to its user); before any computation starts the backend
    configure_xla()
    # and holds the host BLAS to one thread: its small SVDs beside XLA's threads spun for
    # a core (`_core.blas`; a user's OPENBLAS_NUM_THREADS / OMP_NUM_THREADS is kept)
    limit_blas()
    release()  # Ctrl-C from here on is caught below (and remembered: `_interrupt`)
    rc, returned = EXIT_CODE, False
    try:
        rc = _run(argv)
        returned = True
        return rc
    finally:
        stopped = interrupted()
        restore()
        if launched_as_cli():  # not a test or a program calling main: it goes on
            if stopped and rc == EXIT_CODE:
                # an interrupted run has said its line and written nothing after it
                # (outputs are atomic); the interpreter's finalisation would race XLA's
                # native threads still compiling or running, and crashed with SIGSEGV
                # after the line on CI (2026-11-28): end the process here
                sys.stdout.flush()
                sys.stderr.flush()
                os._exit(rc)
            shutting_down(rc)
            if returned:  # not an exit on its way (argparse's --help: SystemExit(0))
                end_process(rc)


def _run(argv) -> int:

    argv = sys.argv[1:] if argv is None else [str(a) for a in argv]
    try:
        ap = build_parser(argv[0] if argv else None)
        args = ap.parse_args(join_negative_values(argv, value_options(ap)))
        _enable_cache()
        args.verb.execute(args)
        if interrupted():  # a Ctrl-C whose exception was dropped (a gc callback ate it)
            raise KeyboardInterrupt
    except InputError as e:
        # the library names its arguments; the command line words them as its options
        print(f"jaxwear: error: {_one_line(e.worded(option_words()))}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # one line, exit 1 (`jaxwear._core.interrupt`)
        print(MESSAGE, file=sys.stderr)
        return EXIT_CODE
    except Exception as e:  # one line, never a traceback, unless asked for
        if interrupted():  # Python wrapped the interrupt (a class body's __set_name__)
            print(MESSAGE, file=sys.stderr)
            return EXIT_CODE
        if os.environ.get("JAXWEAR_DEBUG"):
            raise

        if isinstance(e, OSError) and not isinstance(e, NoSpaceError) and e.errno in FULL:
            # a full device met outside the outputs' writes (those name their file)
            e = NoSpaceError(e.filename or "a file being written", e.errno)
        where = effect_file_frame(e)  # an effect from a file that failed inside a run
        # jaxwear's own failures say what happened in words; anything else is a fault of
        # the program, said as one (the exception's name is for the bug report); an
        # exception raised in a user's effect file is that file's, named where it was
        what = (_one_line(e) if isinstance(e, OWN_FAILURES) else
                f"{type(e).__name__}: {_one_line(e)}" if where else
                f"internal error ({type(e).__name__}: {_one_line(e)}); please report it "
                f"with the study (JAXWEAR_DEBUG=1 shows the traceback)")
        print(f"jaxwear: {where + ': ' if where else ''}{what}", file=sys.stderr)
        return 1
    return 0


# failures of a run that jaxwear names itself (exit 1, the message alone)
OWN_FAILURES = (FitError, ModelFailure, TrialFailed, WornThroughError, NoSpaceError)


def _one_line(e) -> str:
    return " ".join(str(e).splitlines())


# Library arguments whose option has another name (the rest: `train_until` -> --train-until)
_RENAMED = {"fit_spec": "--fit", "json_file": "--json", "for_keys": "--for"}


@functools.cache
def option_words() -> dict:
    """Python argument name -> the option that sets it, over every verb (argparse's dest)."""
    words = dict(_RENAMED)
    for action in build_parser()._actions:
        for sub in getattr(action, "choices", None) or {}:
            for a in action.choices[sub]._actions:
                if a.option_strings:
                    words.setdefault(a.dest, max(a.option_strings, key=len))
    return words


__all__ = ["build_parser", "main"]
