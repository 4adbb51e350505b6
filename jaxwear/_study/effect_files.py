"""User effects from files: `[model] effect_files = ["my_effects.py"]` (design.md §7).

A study lists Python files (paths relative to the study file); `load_study` loads them
before it builds anything else, and every `jaxwear.Effect` subclass a file defines with a
non-empty `name` is registered (`register_effect`), so every verb (simulate, calibrate,
diagnose, synth --conditions, sweep, sensitivity, predict) knows it: `effects = ["name"]`
switches one on, and one that is not switched on is a diagnose candidate like the built-ins.

Loading is idempotent. A file is executed once per content (its SHA-256): the same file
named twice, or by two studies in one process, registers the same effect objects again. A
file edited between two loads replaces the effects it registered before. A *different*
class under a name or parameter key that is taken (by another file, a built-in, or an
effect registered from Python) is bad input naming both files.

Errors are `InputError` (exit 2) naming the file, the line and what was expected: a
missing file (the study's line), a syntax error (its line), an exception while the file
runs (the line of the last frame in that file, one line, no traceback), no Effect
subclass, an effect that `register_effect` refuses (its message). The file is read and
compiled in memory: nothing is written beside it (no `__pycache__`).
"""

from __future__ import annotations

import ast
import hashlib
import inspect
import re
import sys
import types
from pathlib import Path

from jaxwear._core.errors import InputError
from jaxwear._physics.effects import _base
from jaxwear._physics.effects._base import (
    EFFECT_ORIGINS,
    Effect,
    register_effect,
    registered_effects,
)
from jaxwear._study.effect_check import check_effect

KEY = "model.effect_files"
_PACKAGE = "jaxwear_effect_files"  # sys.modules prefix of loaded files

# resolved path -> (sha256 of the source, the effects it registered)
_LOADED: dict[Path, tuple[str, tuple[Effect, ...]]] = {}
# effect name -> (resolved path, the effect object registered from it)
_ORIGIN = EFFECT_ORIGINS  # name -> (file, effect), in the registry's module


def effect_file_names(study) -> list[str]:
    """The `effect_files` entries of a study as written (strings only; `[]` if none)."""
    model = (getattr(study, "raw", None) or {}).get("model", {})
    names = model.get("effect_files", []) if isinstance(model, dict) else []
    return [n for n in names if isinstance(n, str)] if isinstance(names, list) else []


def effect_file_paths(study) -> list[Path]:
    """The effect files a study names, as paths (relative to the study's folder): inputs
    that no output may replace (`jaxwear._study.outputs.input_files`)."""
    folder = Path(study.path).parent
    return [folder / n for n in effect_file_names(study)]


def load_effect_files(study_path, names) -> tuple[Path, ...]:
    """Load the `[model] effect_files` of the study at `study_path` (`names` as written in
    it) and register their effects. Returns the files' paths.

    Raises `InputError` naming the study (and the line of `effect_files` in it) for a value
    that is not a list of file names or a file that does not exist, and naming the effect
    file and line for everything `load_effect_file` refuses."""
    study_path = Path(study_path)
    where = f"{study_path}: {_line_of(study_path)}{KEY}"
    if not isinstance(names, list) or not all(isinstance(n, str) and n.strip() for n in names):
        raise InputError(f"{where} must be a list of Python file names (relative to the "
                         f"study), e.g. [\"my_effects.py\"]; got {names!r}")
    paths = []
    for name in names:
        f = study_path.parent / name
        if not f.exists():
            raise InputError(f"{where}: effect file {name!r} not found (looked for {f})")
        if not f.is_file():
            raise InputError(f"{where}: {name!r} is not a file (looked for {f})")
        load_effect_file(f)
        paths.append(f)
    return tuple(paths)


def load_effect_file(path) -> tuple[Effect, ...]:
    """Execute the Python file at `path` and register every `Effect` subclass it defines
    with a non-empty `name` (one object each, made without arguments). Returns them.

    Idempotent per file content (see the module docstring). Raises `InputError` (file,
    line, what was expected)."""
    path = Path(path)
    resolved = path.resolve()
    try:
        raw = resolved.read_bytes()
        source = raw.decode("utf-8-sig")
    except OSError as e:
        raise InputError(f"{path}: cannot read the effect file ({e.strerror or e})") from None
    except UnicodeDecodeError as e:
        line = raw.count(b"\n", 0, e.start) + 1
        raise InputError(f"{path}: line {line}: not UTF-8; save the effect file as UTF-8"
                         ) from None
    digest = hashlib.sha256(raw).hexdigest()
    cached = _LOADED.get(resolved)
    if cached is not None and cached[0] == digest:
        _check_conflicts(path, resolved, cached[1], {})
        for eff in cached[1]:  # again, in case one was unregistered since
            if registered_effects().get(eff.name) is not eff:
                _register(path, eff, _class_line(eff, {}))
        return cached[1]

    try:
        tree = ast.parse(source, filename=str(resolved))
        code = compile(tree, str(resolved), "exec", dont_inherit=True)
    except SyntaxError as e:
        raise InputError(f"{path}: line {e.lineno}: syntax error ({e.msg}); expected Python "
                         f"that defines jaxwear.Effect subclasses") from None
    except ValueError as e:  # e.g. a NUL byte
        raise InputError(f"{path}: {e}; expected Python source") from None
    class_lines = {n.name: n.lineno for n in tree.body if isinstance(n, ast.ClassDef)}
    stem = re.sub(r"\W", "_", resolved.stem)
    module = types.ModuleType(f"{_PACKAGE}.{stem}_{digest[:12]}")
    module.__file__ = str(resolved)
    sys.modules[module.__name__] = module  # dataclasses and pickling look classes up here
    before = dict(_base._REGISTRY)
    try:
        exec(code, module.__dict__)
    except (Exception, SystemExit) as e:
        sys.modules.pop(module.__name__, None)
        line = _raising_line(e, str(resolved))
        msg = " ".join(str(e).split()) or "(no message)"
        raise InputError(f"{path}: line {line}: {type(e).__name__}: {msg} (raised while "
                         f"loading the effect file)") from None
    finally:
        # A file may call register_effect itself (the examples do): the registry is put
        # back, and the classes it defines are registered below with the checks.
        _base._REGISTRY.clear()
        _base._REGISTRY.update(before)

    classes = []
    for obj in vars(module).values():
        if (isinstance(obj, type) and issubclass(obj, Effect) and obj.name
                and obj.__module__ == module.__name__ and obj not in classes):
            classes.append(obj)
    if not classes:
        raise InputError(f"{path}: defines no jaxwear.Effect subclass with a `name`; expected "
                         f"e.g. `class MyWear(jaxwear.Effect): name = \"my_wear\"` with a "
                         f"strength parameter and a hook (docs/effects.md)")
    effects = []
    for cls in classes:
        line = class_lines.get(cls.__qualname__, _class_line(cls, class_lines))
        try:
            effects.append(cls())
        except Exception as e:
            raise InputError(f"{path}: line {line}: {cls.__name__}() failed ({e}); an effect "
                             f"must be constructible without arguments") from None
    _check_conflicts(path, resolved, effects, class_lines)
    for eff in effects:  # each hook tried once, before anything is registered
        check_effect(path, eff, _class_line(eff, class_lines))
    # A new version of a file replaces what its old version registered.
    for name, (origin, eff) in list(_ORIGIN.items()):
        if origin == resolved and registered_effects().get(name) is eff:
            _base.unregister_effect(name)
    done = []
    try:
        for eff in effects:
            _register(path, eff, _class_line(eff, class_lines))
            done.append(eff)
    except InputError:
        for eff in done:
            _base.unregister_effect(eff.name)
        raise
    for eff in effects:
        _ORIGIN[eff.name] = (resolved, eff)
    _LOADED[resolved] = (digest, tuple(effects))
    return tuple(effects)


def _register(path: Path, eff: Effect, line: int) -> None:
    try:
        register_effect(eff)
    except ValueError as e:
        raise InputError(f"{path}: line {line}: {e}") from None


def _check_conflicts(path: Path, resolved: Path, effects, class_lines) -> None:
    """A name or parameter key taken by an effect from elsewhere: `InputError` naming both."""
    here = {}
    for eff in effects:
        line = _class_line(eff, class_lines)
        if eff.name in here:
            raise InputError(f"{path}: line {line}: effect name {eff.name!r} is defined twice "
                             f"in this file (also at line {here[eff.name]})")
        here[eff.name] = line
        other = registered_effects().get(eff.name)
        if other is not None and _origin(other) != resolved:
            raise InputError(f"{path}: line {line}: effect name {eff.name!r} is taken by "
                             f"{type(other).__name__} from {_origin(other)}; rename one of "
                             f"them")
    owners = {}
    for eff in effects:
        for key in eff.parameters:
            if key in owners and owners[key].name != eff.name:
                raise InputError(f"{path}: line {_class_line(eff, class_lines)}: parameter "
                                 f"{key!r} of effect {eff.name!r} also belongs to effect "
                                 f"{owners[key].name!r} in this file")
            owners[key] = eff
    for eff in effects:
        for other in registered_effects().values():
            if other.name == eff.name or _origin(other) == resolved:
                continue
            for key in eff.parameters:
                if key in other.parameters:
                    raise InputError(
                        f"{path}: line {_class_line(eff, class_lines)}: parameter {key!r} of "
                        f"effect {eff.name!r} already belongs to effect {other.name!r} from "
                        f"{_origin(other)}; rename one of them")


def _origin(eff: Effect) -> Path | str:
    """The file an effect was registered from: its effect file, or its class's source."""
    entry = _ORIGIN.get(eff.name)
    if entry is not None and entry[1] is eff:
        return entry[0]
    try:
        return Path(inspect.getfile(type(eff))).resolve()
    except (TypeError, OSError):
        return f"module {type(eff).__module__}"


def _class_line(obj, class_lines) -> int:
    cls = obj if isinstance(obj, type) else type(obj)
    if cls.__qualname__ in class_lines:
        return class_lines[cls.__qualname__]
    try:
        return inspect.getsourcelines(cls)[1]
    except (TypeError, OSError):
        return 1


def _raising_line(exc: BaseException, filename: str) -> int:
    """Line of the innermost traceback frame in `filename` (where the user's code failed)."""
    line, tb = 1, exc.__traceback__
    while tb is not None:
        if tb.tb_frame.f_code.co_filename == filename:
            line = tb.tb_lineno
        tb = tb.tb_next
    return line


def _line_of(study_path: Path) -> str:
    """"line N: " of the study's `effect_files =` (tomllib gives no positions), or ""."""
    try:
        lines = study_path.read_text(encoding="utf-8-sig").splitlines()
    except (OSError, UnicodeDecodeError):
        return ""
    for i, text in enumerate(lines, start=1):
        if re.match(r"\s*effect_files\s*=", text):
            return f"line {i}: "
    return ""


def effect_file_frame(exc: BaseException) -> str | None:
    """"FILE: line N: in FUNCTION" of the innermost traceback frame of `exc` in a loaded
    effect file, or None: an effect that passed the load-time check (`_check`) and fails
    later, inside a run (other strengths, traced by jit), is named by its file (issue 41)."""
    files = {str(p) for p in _LOADED}
    found, tb = None, exc.__traceback__
    while tb is not None:
        code = tb.tb_frame.f_code
        if code.co_filename in files:
            found = f"{code.co_filename}: line {tb.tb_lineno}: in {code.co_name}"
        tb = tb.tb_next
    cause = exc.__cause__ or exc.__context__
    if found is None and cause is not None and cause is not exc:
        return effect_file_frame(cause)
    return found


