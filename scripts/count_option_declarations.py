"""Count where each option of the ``procam`` command is declared, in this tree or another checkout of it.

    python scripts/count_option_declarations.py            # this tree
    python scripts/count_option_declarations.py OTHER_TREE  # e.g. an older commit: git worktree add /tmp/old REV

An option is a flag of the command (``--schedule``). Its declarations are counted by reading the code, not
running it: a literal ``add_argument("--flag"`` in ``addon/cli/``, a ``--flag`` key of a message table in
``operators/``, a ``procam_<name>`` property written in ``panels/properties.py``, and the ``Options`` field of a
step (``addon/steps/``) that holds it. A field declared with ``options.option(...)`` counts once: the parser, the
property and the message name are made from it.
"""

from __future__ import annotations

import ast
import re
import sys
from collections import Counter
from pathlib import Path


def _declared_fields(steps: Path) -> dict[str, int]:
    """Flags declared by ``option(...)`` fields: flag → 1 (the field is the declaration)."""
    out: dict[str, int] = {}
    for path in steps.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.AnnAssign) and isinstance(node.value, ast.Call) \
                    and getattr(node.value.func, "id", "") in ("option", "same_option"):
                name = node.target.id if isinstance(node.target, ast.Name) else ""
                kw = {k.arg: k.value for k in node.value.keywords}
                flag = kw.get("negate") or kw.get("flag")
                text = flag.value if isinstance(flag, ast.Constant) else "--" + name.replace("_", "-")
                if text:
                    out[text] = 1
    return out


def count(root: Path) -> tuple[Counter[str], dict[str, int]]:
    places: Counter[str] = Counter()
    declared = _declared_fields(root / "addon" / "steps")
    places.update(declared)
    fields = set()
    for path in (root / "addon" / "steps").glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and node.name.endswith("Options"):
                fields |= {n.target.id for n in node.body if isinstance(n, ast.AnnAssign)
                           and isinstance(n.target, ast.Name)}
    for path in (root / "addon" / "cli").glob("*.py"):
        for flag in re.findall(r"add_argument\(\s*\"(--[a-z][a-z0-9-]*)\"", path.read_text()):
            places[flag] += 1
            name = flag[2:].replace("-", "_")
            if flag not in declared and (name in fields or name.removeprefix("no_") in fields):
                places[flag] += 1  # the hand-written parser line beside the step's field
    for path in (root / "operators").glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Dict):
                for key in node.keys:
                    if isinstance(key, ast.Constant) and isinstance(key.value, str) and key.value in places:
                        places[key.value] += 1
    props = (root / "panels" / "properties.py").read_text()
    for flag in list(places):
        if flag not in declared and f'"procam_{flag[2:].replace("-", "_")}"' in props:
            places[flag] += 1
    return places, declared


def main(argv: list[str]) -> int:
    root = Path(argv[1] if len(argv) > 1 else Path(__file__).resolve().parents[1])
    places, declared = count(root)
    # Every command names its own output folder and its replace switch: counted apart.
    own = {f: places.pop(f) for f in ("--out", "--force") if f in places}
    most = places.most_common(5)
    print(f"{root}: {len(places)} options, {sum(places.values())} declarations "
          f"({len(declared)} options declared once on their Options field)")
    print("most declared: " + ", ".join(f"{f} {n}" for f, n in most))
    print("options declared in more than one place: " + str(sum(1 for n in places.values() if n > 1)))
    print("apart: " + ", ".join(f"{f} {n} (one per command that writes a folder, with its messages)"
                                for f, n in own.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
