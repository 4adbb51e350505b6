"""Which files a study was read from, and the output folder of a verb opened against them (never
over an input)."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from jaxwear._core.io import OutputDir
from jaxwear._study.effect_files import effect_file_paths


def input_files(study) -> list[Path]:
    """The files a study was read from: the study file, its effect files, its load files
    and its profile/history CSVs (those that exist; a study made in memory, like synth's
    paper conditions, has none)."""

    files = [Path(study.path), *effect_file_paths(study)] if getattr(study, "path", None) else []
    for block in getattr(getattr(study, "config", None), "duty_cycle", ()):
        if getattr(block, "load", None) is not None:  # a load_history study's load files
            files.append(Path(block.load.path))
    for e in study.experiments:
        for d in (e.profile, e.history):
            if d is not None and d.path:
                files.append(Path(d.path))
    return [f for f in files if f.is_file()]


def open_outputs(study, out, *, planned: Iterable[str] = (), json_file=None,
                 extra_inputs: Iterable = ()) -> OutputDir:
    """The one call of every verb, before any work: `open_outputs(study, args.out,
    planned=[...], json_file=args.json)`. Raises `InputError` (exit 2) when an output would
    replace one of the study's input files."""
    return OutputDir(out, [*input_files(study), *extra_inputs], planned=planned,
                     json_file=json_file)


def per_experiment(study, *patterns: str) -> list[str]:
    """File names `pattern.format(name)` for every experiment of the study."""
    return [p.format(e.name) for e in study.experiments for p in patterns]
