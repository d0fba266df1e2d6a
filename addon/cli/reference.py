"""The operations reference (docs/operations.md), written from the ``procam`` parser itself.

Every command, argument, default and choice comes from :func:`app.build_parser`, so the page cannot drift from
the command: ``scripts/gen_ops_reference.py`` writes it and ``tests/test_docs.py`` checks that the committed page
is what the parser gives today.
"""

from __future__ import annotations

import argparse

from . import app

#: Columns for usage lines: fixed, so the page does not depend on the terminal it was made in.
WIDTH = 100

HEADER = """\
# Operations reference

Every `procam` command and option, written from the command's own parser by `python scripts/gen_ops_reference.py`
(do not edit by hand: `tests/test_docs.py` fails when this page differs from what the parser gives). The same
text is on the terminal with `procam COMMAND --help`. Inside Blender every command runs as
`blender --background --command procam COMMAND …`. How the steps fit together is in the
[user guide](user-guide.md); how each works, in [methods](methods.md).
"""


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The subcommands' parsers by name, in the order ``procam --help`` lists them."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _cell(text: str) -> str:
    """One Markdown table cell: no line breaks, pipes escaped."""
    return " ".join(text.split()).replace("|", "\\|")


def _argument(formatter: argparse.HelpFormatter, action: argparse.Action) -> str:
    """How the argument is written: ``--flag VALUE`` (with its aliases) or a positional's name."""
    if not action.option_strings:
        return formatter._format_args(action, formatter._get_default_metavar_for_positional(action))
    if action.nargs == 0:
        return ", ".join(action.option_strings)
    value = formatter._format_args(action, formatter._get_default_metavar_for_optional(action))
    return ", ".join(f"{flag} {value}" for flag in action.option_strings)


def _usage(parser: argparse.ArgumentParser) -> str:
    formatter = argparse.HelpFormatter(parser.prog, width=WIDTH)
    formatter.add_usage(parser.usage, parser._actions, parser._mutually_exclusive_groups)
    return formatter.format_help().strip()


def _command(name: str, parser: argparse.ArgumentParser) -> list[str]:
    formatter = argparse.HelpFormatter(parser.prog, width=WIDTH)
    out = [f"## procam {name}", "", parser.description or "", "", "```text", _usage(parser), "```", ""]
    rows = [a for a in parser._actions if not isinstance(a, argparse._HelpAction) and a.help != argparse.SUPPRESS]
    if rows:
        out += ["| argument | what it does |", "|---|---|"]
        listed: list[tuple[str, str]] = []  # help of several lines (a table of its own): its first line in the cell
        for action in rows:
            help_text = formatter._expand_help(action) if action.help else ""
            argument = _argument(formatter, action)
            first, newline, rest = help_text.partition("\n")
            if newline:
                listed.append((argument, rest))
                help_text = f"{first.rstrip(':')} below the table"
            out.append(f"| `{_cell(argument)}` | {_cell(help_text)} |")
        out.append("")
        for argument, help_text in listed:
            out += [f"`{argument}`:", "", "```text", help_text.strip(), "```", ""]
    if parser.epilog and not parser.epilog.startswith("exit codes:"):  # a command's own notes; the codes are above
        out += ["```text", parser.epilog.strip(), "```", ""]
    return out


def render(parser: argparse.ArgumentParser | None = None) -> str:
    """The whole page as Markdown."""
    parser = parser or app.build_parser()
    commands = _subparsers(parser)
    out = [HEADER, "| command | what it does |", "|---|---|"]
    out += [f"| [`procam {name}`](#procam-{name}) | {_cell(p.description or '')} |" for name, p in commands.items()]
    out += ["", "## Exit codes and environment", "", "The same for every command (`procam --help`):", "",
            "```text", app.EPILOG, "```", ""]
    for name, sub in commands.items():
        out += _command(name, sub)
    return "\n".join(out).rstrip() + "\n"
