"""Headless commands: ``procam …`` in the venv and ``blender --background --command procam …``.

One code path for both: :func:`main` takes an argument list and returns an exit
code; it never raises and never prints a traceback on the terminal. The codes
scripts can rely on (also printed by ``procam --help``):

====  =====================================================================
0     success
1     an unexpected internal error (a bug): one line on stderr, the traceback in a log file it names
2     a problem you can fix (:class:`~procam.addon.errors.ProCamError`: a missing file, a bad
      value, an output that exists without ``--force``), or a usage error from the argument parser
130   cancelled (Ctrl-C, or :class:`~procam.addon.errors.Cancelled`); finished work is kept
====  =====================================================================

Results go to stdout, progress and errors to stderr. Numerical warnings (numpy's
``RuntimeWarning``: a division by zero or an infinity subtracted on pixels that
hold no data) are no news to a user: they go to a log file in PROCAM_LOG_DIR,
not to the terminal (:func:`_warnings_to_log`).
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import tempfile
import time
import traceback
import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

from ..errors import Cancelled, ProCamError

EXIT_OK = 0
EXIT_INTERNAL = 1
EXIT_USER = 2  # also argparse's code for usage errors
EXIT_CANCELLED = 130  # 128 + SIGINT, what shells report for Ctrl-C

EPILOG = f"""\
exit codes:
  {EXIT_OK:<4} success
  {EXIT_INTERNAL:<4} internal error (a bug in ProCam): a one-line message names the log file with the traceback
  {EXIT_USER:<4} a problem you can fix (the message says what to do), or wrong command-line arguments
  {EXIT_CANCELLED:<4} cancelled (Ctrl-C); finished work is kept

Results go to stdout, progress and errors to stderr. `procam COMMAND --help` describes each command.
Inside Blender: blender --background --command procam COMMAND ...
Environment: PROCAM_LOG_DIR (where internal-error logs and numerical warnings go; default the temporary folder),
PROCAM_TRACEBACK=1 (also print the traceback on stderr)."""

Command = tuple[str, str, Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]
_COMMANDS: list[Command] = []


def command(name: str, help_text: str, configure: Callable[[argparse.ArgumentParser], None]):
    """Register a subcommand: ``configure`` adds its arguments, the decorated function runs it."""
    def wrap(run: Callable[[argparse.Namespace], int]):
        _COMMANDS.append((name, help_text, configure, run))
        return run
    return wrap


def _fill_missing_help(parser: argparse.ArgumentParser) -> None:
    """Every option gets a help line, so ``--help`` never lists a bare flag."""
    for action in parser._actions:
        if action.help is not None or isinstance(action, argparse._HelpAction):
            continue
        if action.dest == "seed":
            action.help = "seed of every random stream; the same seed repeats the same result (default %(default)s)"
        elif action.choices:
            action.help = "one of " + ", ".join(map(str, action.choices)) + " (default %(default)s)"
        elif action.default not in (None, argparse.SUPPRESS):
            action.help = "(default %(default)s)"


#: The modules of this package that define subcommands, in the order ``procam --help`` lists them: the workflow's
#: steps first. Imported when the parser is built, because each registers itself with :func:`command`.
COMMAND_MODULES = ("lab", "capture", "live", "calibrate", "precompute", "rig", "compensate", "show", "evaluate",
                   "diagnose", "export", "mpcdi", "report", "demo", "build")


def build_parser() -> argparse.ArgumentParser:
    for module in COMMAND_MODULES:
        importlib.import_module(f"{__package__}.{module}")

    parser = argparse.ArgumentParser(prog="procam",
                                     description="ProCam: projector compensation by differentiable rendering.",
                                     epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    # In COMMAND_MODULES' order whichever module was imported first (a test may import one before this runs).
    order = {f"{__package__}.{m}": i for i, m in enumerate(COMMAND_MODULES)}
    for name, help_text, configure, run in sorted(_COMMANDS, key=lambda c: order.get(c[3].__module__, len(order))):
        p = sub.add_parser(name, help=help_text, description=help_text)
        configure(p)
        _fill_missing_help(p)
        if p.epilog is None:
            p.epilog = f"exit codes: {EXIT_OK} success, {EXIT_USER} a problem you can fix (or bad arguments), " \
                       f"{EXIT_CANCELLED} cancelled, {EXIT_INTERNAL} internal error (see procam --help)"
        p.set_defaults(_run=run)
    return parser


def _crash_log(name: str, exc: BaseException) -> str:
    """Write the traceback of an unexpected error to a log file; its path, or why it could not be written."""
    folder = _log_folder()
    text = "".join(traceback.format_exception(exc))
    try:
        os.makedirs(folder, exist_ok=True)
        fd, path = tempfile.mkstemp(prefix=f"procam-{name}-{time.strftime('%Y%m%d-%H%M%S')}-", suffix=".log",
                                    dir=folder)
        with os.fdopen(fd, "w") as fh:
            fh.write(f"procam {name} failed with an internal error\nargv: {sys.argv!r}\n\n{text}")
        return path
    except OSError as err:
        return f"(not written: {err}); set PROCAM_TRACEBACK=1 to see it"


def _log_folder() -> str:
    return os.environ.get("PROCAM_LOG_DIR") or tempfile.gettempdir()


@contextmanager
def _warnings_to_log(name: str) -> Iterator[None]:
    """While a command runs, numerical warnings (``RuntimeWarning``) are written to a log file
    (``procam-NAME-DATE-….log`` in PROCAM_LOG_DIR, made at the first one) instead of the terminal; other
    warnings are shown as before."""
    previous = warnings.showwarning
    path: list[str] = []

    def show(message: Warning | str, category: type[Warning], filename: str, lineno: int, file: Any = None,
             line: str | None = None) -> None:
        if not issubclass(category, RuntimeWarning):
            previous(message, category, filename, lineno, file, line)
            return
        try:
            if not path:
                os.makedirs(_log_folder(), exist_ok=True)
                fd, made = tempfile.mkstemp(prefix=f"procam-{name}-{time.strftime('%Y%m%d-%H%M%S')}-",
                                            suffix=".log", dir=_log_folder())
                os.close(fd)
                path.append(made)
                with open(made, "w") as fh:
                    fh.write(f"procam {name}: numerical warnings\nargv: {sys.argv!r}\n\n")
            with open(path[0], "a") as fh:
                fh.write(warnings.formatwarning(message, category, filename, lineno, line))
        except OSError:
            pass  # a log that cannot be written: the warning is dropped, never shown to the user

    warnings.showwarning = show
    try:
        yield
    finally:
        warnings.showwarning = previous


def main(argv: Sequence[str] | None = None) -> int:
    """Run one ``procam`` command; returns the exit code (module doc) instead of raising."""
    try:
        parser = build_parser()
    except Exception as exc:  # a command module that does not import: a bug, reported like any other
        return _internal_error("", exc)
    try:
        args = parser.parse_args(list(sys.argv[1:] if argv is None else argv))
    except SystemExit as exc:  # --help (0) or a usage error (2): a code, not an exit, so Blender keeps control
        return exc.code if isinstance(exc.code, int) else (EXIT_OK if exc.code is None else EXIT_USER)
    if not getattr(args, "_run", None):
        parser.print_help()
        return EXIT_OK
    name = args.command
    try:
        with _warnings_to_log(name):
            return int(args._run(args) or 0)
    except Cancelled as exc:
        print(f"procam {name}: cancelled: {exc}", file=sys.stderr)
        return EXIT_CANCELLED
    except ProCamError as exc:
        print(f"procam {name}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"procam {name}: cancelled", file=sys.stderr)
        return EXIT_CANCELLED
    except Exception as exc:
        return _internal_error(name, exc)


def _internal_error(name: str, exc: BaseException) -> int:
    """A bug: a short message on stderr, the details in a log file to attach to a report."""
    where = _crash_log(name or "main", exc)
    if os.environ.get("PROCAM_TRACEBACK"):
        traceback.print_exception(exc, file=sys.stderr)
    who = f"procam {name}" if name else "procam"
    print(f"{who}: internal error: {type(exc).__name__}: {exc}\n"
          f"{who}: this is a bug in ProCam; the traceback is in {where}", file=sys.stderr)
    return EXIT_INTERNAL


if __name__ == "__main__":
    sys.exit(main())
