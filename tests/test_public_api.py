"""The public API: every name of `jaxwear.__all__` imports, the README's Python block runs,
and neither the README nor the examples import a private module."""

import ast
import contextlib
import io
import re
from pathlib import Path

import jaxwear

ROOT = Path(__file__).resolve().parents[1]
PRIVATE = re.compile(r"(from|import)\s+jaxwear\.(_\w+|effects\._\w+)")


def test_every_name_in_all_imports_and_is_documented():
    assert len(set(jaxwear.__all__)) == len(jaxwear.__all__)
    ns = {}
    exec("from jaxwear import *", ns)  # noqa: S102
    assert set(ns) - {"__builtins__"} == set(jaxwear.__all__)
    for name in jaxwear.__all__:
        obj = getattr(jaxwear, name)
        doc = (obj.__doc__ or "").strip()
        assert doc, f"jaxwear.{name} has no docstring"
        # a dataclass without a docstring of its own gets its signature as __doc__
        assert not doc.startswith(f"{name}("), f"jaxwear.{name} has only a generated docstring"


def test_public_names_defined_in_the_package_are_in_all():
    # a name imported into jaxwear/__init__.py without an underscore is meant for users
    tree = ast.parse((ROOT / "jaxwear" / "__init__.py").read_text())
    exported = {a.asname or a.name for node in tree.body if isinstance(node, ast.ImportFrom)
                and (node.module or "").startswith("jaxwear") for a in node.names
                if not (a.asname or a.name).startswith("_")}
    # and the names imported on first use (`_LAZY`: the diagnose package is not imported
    # with jaxwear)
    exported |= set(jaxwear._LAZY)
    assert exported == set(jaxwear.__all__)


def _python_blocks(text):
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


def test_readme_and_examples_import_no_private_module():
    files = [ROOT / "README.md", *sorted((ROOT / "calibration" / "examples").glob("*.py"))]
    for f in files:
        hits = PRIVATE.findall(f.read_text())
        assert not hits, f"{f.relative_to(ROOT)} imports private jaxwear modules: {hits}"


def _small_boom(folder):
    """calibration/boom's study at 48 nodes x 36 steps (its data file beside it)."""
    src = ROOT / "calibration" / "boom"
    text = (src / "study.toml").read_text()
    text, n = re.subn(r"nodes = 90\nsteps_per_rev = 72", "nodes = 48\nsteps_per_rev = 36", text)
    assert n == 1, "calibration/boom/study.toml changed: update this test's grid substitution"
    (folder / "study.toml").write_text(text)
    (folder / "boom.csv").write_text((src / "boom.csv").read_text())
    return folder / "study.toml"


def test_readme_python_block_runs(tmp_path):
    blocks = _python_blocks((ROOT / "README.md").read_text())
    assert blocks, "the README has no ```python block"
    code = blocks[0]
    # The block as written uses the paper's 360 x 360 grid; the same code on a small grid
    # keeps the test fast (every line still runs, the gradient included).
    small, n = re.subn(r"nodes=360, steps_per_rev=360", "nodes=48, steps_per_rev=48", code)
    assert n == 1, "the README block changed: update this test's grid substitution"
    # likewise the boom study's 90 x 72 grid (a copy at 48 x 36 in a temporary folder)
    small, n = re.subn(r'"calibration/boom/study.toml"', repr(str(_small_boom(tmp_path))),
                       small)
    assert n == 1, "the README block changed: update this test's boom substitution"
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(small, "README.md", "exec"), {})  # noqa: S102
    lines = out.getvalue().splitlines()
    assert len(lines) == 3 and "µm" in lines[0], lines
    depth_um = float(lines[0].split()[0])
    assert 0 < depth_um < 100  # a 10⁴-revolution rig run wears microns, not millimetres
    grad = float(lines[1])
    # d ln(peak)/d ln(K_d) is in (0, 1]: more wear, and at most proportionally more (the
    # bore conforms to the pin as it wears, which lowers the peak pressure)
    elasticity = grad * 1e-13 / (depth_um * 1e-6)
    assert 0.3 < elasticity <= 1.0 + 1e-9, elasticity
    # the boom forecast: every band holds its forecast, and 25 h is deeper than 20 h
    preds = ast.literal_eval(lines[2])
    assert [p["at"] for p in preds] == [20.0, 25.0]
    for p in preds:
        assert p["lower_um"] < p["depth_um"] < p["upper_um"]
    assert preds[1]["depth_um"] > preds[0]["depth_um"]
