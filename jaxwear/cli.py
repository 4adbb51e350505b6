"""Command line: `jaxwear simulate|calibrate|diagnose|synth|sweep|sensitivity` (DESIGN §7).

Exit codes: 0 done, 2 bad input (one line naming the file, key or line), 1 anything else.
Set JAXWEAR_DEBUG=1 to see tracebacks.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path


def _enable_cache():
    # A persistent compilation cache makes the second start of the CLI fast. Opt out with
    # JAXWEAR_NO_CACHE=1. This is the CLI's choice; the library never touches it.
    if os.environ.get("JAXWEAR_NO_CACHE"):
        return
    import jax

    cache = os.environ.get("JAXWEAR_CACHE_DIR",
                           str(Path.home() / ".cache" / "jaxwear" / "jax-compilation"))
    try:
        jax.config.update("jax_compilation_cache_dir", cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    except Exception:  # an unwritable home is no reason to fail
        pass


def cmd_simulate(args):
    from ._budget import check_work
    from ._io import open_outputs
    from ._simulate_study import simulate_outputs, simulate_study
    from ._study import load_study

    study = load_study(args.study)
    out = open_outputs(study, args.out, planned=simulate_outputs(study))
    check_work(study)
    simulate_study(study, out)
    print(f"wrote {out.root / 'profiles.csv'}")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="jaxwear", description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="verb", required=True)

    s = sub.add_parser("simulate", help="predict wear profiles for a study")
    s.add_argument("study", help="study file (TOML)")
    s.add_argument("--out", default="jaxwear_out", help="output folder (default jaxwear_out)")
    s.set_defaults(func=cmd_simulate)

    from ._cli_verbs import add_verbs

    add_verbs(sub)
    return ap


def main(argv=None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    from ._errors import InputError

    _enable_cache()
    try:
        args.func(args)
    except InputError as e:
        print(f"jaxwear: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("jaxwear: interrupted", file=sys.stderr)
        return 1
    except Exception as e:  # one line, never a traceback, unless asked for
        if os.environ.get("JAXWEAR_DEBUG"):
            raise
        print(f"jaxwear: {type(e).__name__}: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
