"""The documentation is checked like code: every link and anchor resolves, every ``procam`` command in a code block
parses with the real parser, every script, test and module it names exists, the operations reference is what the
parser gives, and the README stays a front page.

``python tests/test_docs.py`` prints how much was checked.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import shlex
import sys
import unicodedata
from pathlib import Path

import pytest

from procam.addon.cli.app import build_parser
from procam.addon.cli.reference import render

ROOT = Path(__file__).resolve().parents[1]
#: A front page for artists and show crews; methods and measurements live in docs/.
README_MAX_LINES = 220
#: Pages of other branches waiting to be placed into the docs tree are not part of it yet.
INCOMING = ROOT / "docs" / "incoming"
#: Commands the docs announce before they are merged; a name leaves this set the day it becomes a command
#: (``test_a_pending_command_is_not_one_yet`` says so).
PENDING_COMMANDS: set[str] = set()

LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^\s*```([\w-]*)\s*$")
INLINE_CODE = re.compile(r"(?<!`)`([^`\n]+)`(?!`)")
PATH = re.compile(r"(?<![\w./-])((?:scripts|tests|addon|operators|panels)/[\w/.-]*\w\.(?:py|sh))\b")


def pages() -> list[Path]:
    """README.md, CHANGELOG.md and every Markdown page under docs/ (docs/incoming/ excepted)."""
    out = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    if (ROOT / "CHANGELOG.md").is_file():
        out.append(ROOT / "CHANGELOG.md")
    return [p for p in out if not p.is_relative_to(INCOMING)]


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"`|\*\*|__", "", heading.strip()).lower()
    text = "".join(c for c in text if c in " -_" or unicodedata.category(c)[0] in "LN")
    return text.replace(" ", "-")


def split_blocks(text: str) -> tuple[list[str], list[tuple[str, int, str]]]:
    """The prose lines (code blocks blanked, so line numbers hold) and the code blocks' lines (language, number,
    text)."""
    prose: list[str] = []
    code: list[tuple[str, int, str]] = []
    lang = None
    for number, line in enumerate(text.splitlines(), 1):
        fence = FENCE.match(line)
        if fence:
            lang = None if lang is not None else fence.group(1)
            prose.append("")
        elif lang is not None:
            code.append((lang, number, line))
            prose.append("")
        else:
            prose.append(line)
    return prose, code


def anchors(path: Path) -> set[str]:
    """Every heading's anchor in a page (a repeated heading gets -1, -2 … as on GitHub)."""
    prose, _ = split_blocks(path.read_text(encoding="utf-8"))
    seen: dict[str, int] = {}
    out = set()
    for line in prose:
        m = re.match(r"^(#{1,6})\s+(.*?)\s*#*\s*$", line)
        if not m:
            continue
        base = slug(m.group(2))
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


def _where(page: Path, number: int) -> str:
    return f"{page.relative_to(ROOT) if page.is_relative_to(ROOT) else page.name}:{number}"


def links(among: list[Path]) -> list[tuple[str, Path, str]]:
    """(where, page, target) of every relative link in prose."""
    out = []
    for page in among:
        prose, _ = split_blocks(page.read_text(encoding="utf-8"))
        for number, line in enumerate(prose, 1):
            for target in LINK.findall(INLINE_CODE.sub("", line)):
                if not re.match(r"^[a-z][a-z+.-]*:", target):  # http:, https:, mailto: are not ours to check
                    out.append((_where(page, number), page, target))
    return out


def commands(among: list[Path]) -> list[tuple[str, list[str]]]:
    """(where, argv) of every ``procam …`` line in a code block; a line ending in ``\\`` continues."""
    out = []
    for page in among:
        _, code = split_blocks(page.read_text(encoding="utf-8"))
        pending, start = "", 0
        for _lang, number, line in code:
            if not pending:
                start = number
            pending += line.rstrip()
            if pending.endswith("\\"):
                pending = pending[:-1] + " "
                continue
            text, pending = pending.strip().removeprefix("$ "), ""
            if re.match(r"^(\S*/)?procam(\s|$)", text):
                out.append((_where(page, start), shlex.split(re.split(r"\s#", text)[0])[1:]))
    return out


def inline_commands(among: list[Path]) -> list[tuple[str, str]]:
    """(where, subcommand) of every ``procam NAME`` in inline code (``procam compensate|show`` names two)."""
    out = []
    for page in among:
        prose, _ = split_blocks(page.read_text(encoding="utf-8"))
        for number, line in enumerate(prose, 1):
            for code in INLINE_CODE.findall(line):
                for m in re.finditer(r"(?:^|[\s(])procam ([a-z][a-z|-]*)", code):
                    out += [(_where(page, number), name) for name in m.group(1).split("|") if name]
    return out


def named_paths(among: list[Path]) -> list[tuple[str, str]]:
    """(where, path) of every script, test or module of the repository a page names."""
    out = []
    for page in among:
        for number, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1):
            out += [(_where(page, number), m) for m in PATH.findall(line)
                    if not re.search(r"/[A-Z]+\.\w+$", m)]  # addon/steps/NAME.py is a placeholder
    return out


def script_runs(among: list[Path]) -> list[tuple[str, str, list[str]]]:
    """(where, script, flags) of every ``python scripts/X.py --flag …`` line in a code block."""
    out = []
    for page in among:
        _, code = split_blocks(page.read_text(encoding="utf-8"))
        for _lang, number, line in code:
            m = re.search(r"python\S*\s+(scripts/\S+\.py)(.*)", line.split(" #")[0])
            if m:
                out.append((_where(page, number), m.group(1), re.findall(r"(?<!\S)--[\w-]+", m.group(2))))
    return out


def _subcommands(parser: argparse.ArgumentParser) -> set[str]:
    return next(set(a.choices) for a in parser._actions if isinstance(a, argparse._SubParsersAction))


def bad_links(among: list[Path]) -> list[str]:
    bad = []
    cache: dict[Path, set[str]] = {}
    for where, page, target in links(among):
        file, _, anchor = target.partition("#")
        dest = (page.parent / file).resolve() if file else page
        if not dest.exists():
            bad.append(f"{where}: {target} (no such file)")
        elif anchor and dest.suffix == ".md" and anchor not in cache.setdefault(dest, anchors(dest)):
            bad.append(f"{where}: {target} (no heading with that anchor)")
    return bad


def bad_commands(parser: argparse.ArgumentParser, among: list[Path]) -> list[str]:
    bad = []
    for where, argv in commands(among):
        err = io.StringIO()
        try:
            with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
                parser.parse_args(argv)
        except SystemExit as exc:
            if exc.code not in (0, None):  # --help exits 0
                bad.append(f"{where}: procam {' '.join(argv)}: {err.getvalue().strip().splitlines()[-1]}")
    names = _subcommands(parser) | PENDING_COMMANDS
    return bad + [f"{where}: procam {name}" for where, name in inline_commands(among) if name not in names]


def bad_paths(among: list[Path]) -> list[str]:
    bad = [f"{where}: {path}" for where, path in named_paths(among) if not (ROOT / path).exists()]
    for where, script, flags in script_runs(among):
        source = (ROOT / script).read_text(encoding="utf-8") if (ROOT / script).is_file() else ""
        bad += [f"{where}: {script} {flag}" for flag in flags if f'"{flag}"' not in source]
    return bad


@pytest.fixture(scope="module")
def parser() -> argparse.ArgumentParser:
    return build_parser()


def test_every_relative_link_and_anchor_resolves():
    assert len(links(pages())) > 50  # the pages link to each other; a reader that finds none is broken
    assert bad_links(pages()) == []


def test_every_procam_command_named_parses_with_the_real_parser(parser):
    assert len(commands(pages())) > 30 and len(inline_commands(pages())) > 30
    assert bad_commands(parser, pages()) == []


def test_a_pending_command_is_not_one_yet(parser):
    assert PENDING_COMMANDS & _subcommands(parser) == set(), "it is a command now: take it out of PENDING_COMMANDS"


def test_every_script_test_and_module_named_exists_and_takes_the_flags_given():
    assert len(named_paths(pages())) > 30
    assert bad_paths(pages()) == []


def test_the_operations_reference_is_what_the_parser_gives(parser):
    page = ROOT / "docs" / "operations.md"
    assert page.read_text(encoding="utf-8") == render(parser), \
        "docs/operations.md is stale: run `python scripts/gen_ops_reference.py`"


def test_a_help_of_several_lines_is_listed_below_its_table_not_in_one_cell(parser):
    lab = render(parser).split("## procam lab")[1].split("\n## ")[0]
    row = next(line for line in lab.splitlines() if line.startswith("| `--effects"))
    assert row.endswith("below the table |") and len(row) < 300
    assert "```text\nresponse [projector]: projector response curve" in lab


def test_every_command_has_a_section_in_the_reference(parser):
    names = _subcommands(parser)
    assert {f"procam-{n}" for n in names} <= anchors(ROOT / "docs" / "operations.md")


def test_the_readme_is_a_front_page():
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= README_MAX_LINES
    # the two commands come first, verbatim: .ci/run runs the second
    block = lines[lines.index("```bash") + 1:lines.index("```bash") + 3]
    assert [line.split("#")[0].strip() for line in block] == ["bash scripts/demo.sh", "bash scripts/test.sh"]
    assert "bash scripts/test.sh" in (ROOT / ".ci" / "run").read_text()


def test_the_checks_find_what_is_wrong(parser, tmp_path):
    """Each check above, on a page made to fail once for every kind of fault."""
    page = tmp_path / "page.md"
    page.write_text("# Title `--x`\n\n[ok](#title---x) [gone](#nowhere) [file](missing.md) [web](https://x.org)\n\n"
                    "`procam calibrate` and `procam no-such-step`; scripts/no_such_script.py\n\n"
                    "```bash\nprocam calibrate caps --out cal --no-such-flag   # a comment\n"
                    "procam show cal frames/shot_####.png --out shows/x\n"
                    "python scripts/gen_ops_reference.py --check --no-such-flag\n```\n", encoding="utf-8")
    assert [b.split(": ", 1)[1] for b in bad_links([page])] == \
        ["#nowhere (no heading with that anchor)", "missing.md (no such file)"]
    found = bad_commands(parser, [page])
    assert len(found) == 2 and "--no-such-flag" in found[0] and found[1].endswith("procam no-such-step")
    assert [b.split(": ", 1)[1] for b in bad_paths([page])] == \
        ["scripts/no_such_script.py", "scripts/gen_ops_reference.py --no-such-flag"]


def figures() -> dict[str, int]:
    """How much the checks above cover."""
    among = pages()
    return {"README lines": len((ROOT / "README.md").read_text(encoding="utf-8").splitlines()),
            "pages": len(among), "links and anchors": len(links(among)), "commands parsed": len(commands(among)),
            "commands named inline": len(inline_commands(among)), "paths named": len(named_paths(among)),
            "script runs": len(script_runs(among))}


if __name__ == "__main__":
    for key, value in figures().items():
        print(f"{key}: {value}")
    sys.exit(0)
