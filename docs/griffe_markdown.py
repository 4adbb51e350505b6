"""Griffe extension for the API page: a list in a docstring renders as a list.

The package's docstrings open their lists right under a line of text (`**Arguments:**` then
`- name: ...`), as GitHub's Markdown allows. Python-Markdown, which mkdocs uses, needs a blank
line before a list, or the items run on as one paragraph. This extension inserts that blank
line when the docstrings are loaded; the docstrings themselves are left as written.
"""

import griffe


def blank_line_before_lists(text: str) -> str:
    out: list[str] = []
    fenced = False
    for line in text.split("\n"):
        if line.lstrip().startswith("```"):
            fenced = not fenced
        starts_list = line.startswith(("- ", "* ", "1. "))
        prev = out[-1] if out else ""
        in_list = prev.startswith(("- ", "* ", "1. ", " ", "\t"))
        if not fenced and starts_list and prev.strip() and not in_list:
            out.append("")
        out.append(line)
    return "\n".join(out)


class BlankLineBeforeLists(griffe.Extension):
    def on_instance(self, *, obj, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = blank_line_before_lists(obj.docstring.value)
