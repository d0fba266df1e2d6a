"""Headless commands: ``procam …`` in the venv and ``blender --background --command procam …``.

One code path for both: :func:`main` takes an argument list and returns an exit
code. A :class:`~procam.addon.errors.ProCamError` is printed as one line on
stderr with exit code 2; a bug prints its traceback and exits 1.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

from .errors import ProCamError

Command = tuple[str, str, Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]
_COMMANDS: list[Command] = []


def command(name: str, help_text: str, configure: Callable[[argparse.ArgumentParser], None]):
    """Register a subcommand: ``configure`` adds its arguments, the decorated function runs it."""
    def wrap(run: Callable[[argparse.Namespace], int]):
        _COMMANDS.append((name, help_text, configure, run))
        return run
    return wrap


def build_parser() -> argparse.ArgumentParser:
    from . import commands  # noqa: F401  (registers the subcommands)

    parser = argparse.ArgumentParser(prog="procam", description="ProCam: projector compensation by differentiable rendering.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, help_text, configure, run in _COMMANDS:
        p = sub.add_parser(name, help=help_text, description=help_text)
        configure(p)
        p.set_defaults(_run=run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(list(sys.argv[1:] if argv is None else argv))
    if not getattr(args, "_run", None):
        parser.print_help()
        return 0
    try:
        return int(args._run(args) or 0)
    except ProCamError as exc:
        print(f"procam {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"procam {args.command}: cancelled", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
