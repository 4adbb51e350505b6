"""The tied pair of a diagnosis: `design --from DIAGNOSIS.json` (issue 44: `separate` is the
default goal after a diagnosis with tied alternatives).

A diagnosis document (design.md §7, `diagnose --json`) names what the data cannot tell
apart in two places: `verdict.alternatives` (effects whose evidence is within ln 20 of the
effect found, `verdict.missing_effect`), and the shape's `alternatives` (variables whose AIC
is within ln 20 of its `best`) or its `next_test` (the command `diagnose` wrote for the
best variable and a stand-in that explains nearly as much). The first of these, in that
order (the verdict, the shape on the base fit, the shape on top of the effect found), is
the pair `design` separates.
"""

from __future__ import annotations

from jaxwear._core.errors import InputError
from jaxwear._physics.effects import registered_effects


def _shape_pair(shape) -> list | None:
    if not isinstance(shape, dict) or not shape.get("best"):
        return None
    cmd = shape.get("next_test")
    if isinstance(cmd, str) and "--between " in cmd:
        pair = cmd.split("--between ", 1)[1].split()[0].split(",")
        if len(pair) == 2:
            return pair
    alts = shape.get("alternatives") or []
    if not alts:
        return None
    best = shape["best"] if shape.get("form", "factor") == "factor" else (
        f"deposit:{shape['best']}")
    return [f"shape:{best}", f"shape:{alts[0]}"]


def tied_pair(doc, where: str = "--from") -> tuple[list, str] | None:
    """([A, B], where in the document they come from) of the diagnosis `doc` (a dict
    from its JSON), or None where it names no tie. `InputError` naming `where` for a
    document that is not a diagnosis."""
    if not isinstance(doc, dict) or "verdict" not in doc or not isinstance(
            doc["verdict"], dict):
        raise InputError(f"{where}: expected a diagnosis document (`jaxwear diagnose "
                         f"--json`, with a \"verdict\" object)")
    v = doc["verdict"]
    known = set(registered_effects())
    winner = v.get("missing_effect")
    rivals = [a for a in (v.get("alternatives") or []) if a in known]
    if winner in known and rivals:
        return [winner, rivals[0]], "verdict.alternatives"
    for key in ("shape", "shape_after_effect"):
        pair = _shape_pair(doc.get(key))
        if pair is not None:
            return pair, f"{key}.alternatives"
    return None
