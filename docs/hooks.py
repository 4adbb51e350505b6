"""mkdocs hook: the API page documents exactly the public names.

`docs/api.md` lists one `::: jaxwear.NAME` per name of `jaxwear.__all__`. The list is read
from `jaxwear/__init__.py` as written (no import), so a name added to or removed from the
public API without its entry on the API page fails `mkdocs build` (strict or not).
"""

import ast
import re
from pathlib import Path

from mkdocs.exceptions import PluginError

INIT = Path(__file__).resolve().parents[1] / "jaxwear" / "__init__.py"


def _public_names():
    for node in ast.parse(INIT.read_text(encoding="utf-8")).body:
        if isinstance(node, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets
        ):
            return set(ast.literal_eval(node.value))
    raise PluginError(f"{INIT}: no literal __all__ found")


def on_page_markdown(markdown, page, config, files):
    if page.file.src_uri != "api.md":
        return markdown
    listed = re.findall(r"^::: jaxwear\.(\w+)\s*$", markdown, flags=re.M)
    public = _public_names()
    missing = sorted(public - set(listed))
    extra = sorted(set(listed) - public)
    twice = sorted({n for n in listed if listed.count(n) > 1})
    if missing or extra or twice:
        raise PluginError(
            "docs/api.md must list every name of jaxwear.__all__ once as `::: jaxwear.NAME`: "
            f"missing {missing}, not public {extra}, listed twice {twice}"
        )
    return markdown
