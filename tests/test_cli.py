"""The command-line contract: ``--help`` for every subcommand, exit codes scripts can trust, progress on stderr.

Exit codes (``procam --help``): 0 success, 1 internal error (traceback in a log
file), 2 a user-fixable error or a usage error, 130 cancelled. Nothing here
renders; the end-to-end runs of the commands are in their own test files.
"""

from __future__ import annotations

import argparse
import io
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from procam.addon import errors
from procam.addon.cli import app as cli
from procam.addon.cli import terminal
from procam.addon.cli.app import EXIT_CANCELLED, EXIT_INTERNAL, EXIT_OK, EXIT_USER, main
from procam.addon.cli.terminal import ProgressBar, progress


def _subcommands() -> dict[str, argparse.ArgumentParser]:
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def test_every_subcommand_has_help(capsys):
    commands = _subcommands()
    assert {"lab", "calibrate", "compensate", "show", "patterns", "import-captures", "demo"} <= set(commands)
    for name, parser in commands.items():
        assert main([name, "--help"]) == EXIT_OK, name
        out = capsys.readouterr().out
        assert out.startswith(f"usage: procam {name}") and parser.description and parser.description in " ".join(
            out.split()), name
        assert "exit codes" in out, name
        for action in parser._actions:
            assert action.help and action.help.strip(), f"procam {name}: {action.option_strings or action.dest}"
    assert main(["--help"]) == EXIT_OK
    top = capsys.readouterr().out
    for code in (EXIT_OK, EXIT_INTERNAL, EXIT_USER, EXIT_CANCELLED):
        assert f"\n  {code} " in top
    assert main([]) == EXIT_OK and "COMMAND" in capsys.readouterr().out


def test_exit_codes_agree_with_the_errors():
    assert (EXIT_OK, EXIT_INTERNAL, EXIT_USER, EXIT_CANCELLED) == (0, 1, 2, 130)
    assert errors.ProCamError.exit_code == EXIT_USER and errors.Cancelled.exit_code == EXIT_CANCELLED

    def subclasses(cls):
        for sub in cls.__subclasses__():
            yield sub
            yield from subclasses(sub)

    _subcommands()  # imports every command module, and with them their error classes
    for cls in subclasses(errors.ProCamError):
        expected = EXIT_CANCELLED if issubclass(cls, errors.Cancelled) else EXIT_USER
        assert cls.exit_code == expected, cls


def test_usage_errors_exit_2(capsys):
    for argv in (["no-such-command"], ["show"], ["compensate", "cal"], ["show", "cal", "x", "--out", "o",
                                                                       "--iterations", "many"]):
        assert main(argv) == EXIT_USER, argv
        err = capsys.readouterr().err
        assert "usage:" in err and "Traceback" not in err


@pytest.fixture
def fake_commands(monkeypatch, tmp_path):
    """Commands that fail in each way the contract covers, registered instead of the real ones."""
    monkeypatch.setenv("PROCAM_LOG_DIR", str(tmp_path / "logs"))
    monkeypatch.delenv("PROCAM_TRACEBACK", raising=False)
    failures = {"user": errors.ImageError("target x.png not found; check the path"),
                "cancel": errors.Cancelled("stopped at iteration 3"), "ctrl-c": KeyboardInterrupt(),
                "bug": ZeroDivisionError("division by zero in a stage")}
    table = []
    for name, exc in failures.items():
        def run(args, exc=exc):
            print("partial result")
            raise exc
        table.append((name, f"fails: {name}", lambda p: None, run))
    table.append(("ok", "succeeds", lambda p: p.add_argument("--n", type=int, default=1, help="a number"),
                  lambda args: 0))
    monkeypatch.setattr(cli, "_COMMANDS", table)
    return tmp_path / "logs"


def test_exit_codes_and_messages(fake_commands, capsys):
    expected = {"ok": EXIT_OK, "user": EXIT_USER, "cancel": EXIT_CANCELLED, "ctrl-c": EXIT_CANCELLED,
                "bug": EXIT_INTERNAL}
    for name, code in expected.items():
        assert main([name]) == code, name
        cap = capsys.readouterr()
        assert "Traceback" not in cap.err and "Traceback" not in cap.out, name
        if name == "user":
            assert cap.err.strip() == "procam user: error: target x.png not found; check the path"
        if name in ("cancel", "ctrl-c"):
            assert cap.err.startswith(f"procam {name}: cancelled")
        if name == "bug":
            lines = cap.err.strip().splitlines()
            assert len(lines) == 2 and "internal error: ZeroDivisionError: division by zero in a stage" in lines[0]
            logs = list(fake_commands.glob("procam-bug-*.log"))
            assert len(logs) == 1 and str(logs[0]) in lines[1]
            assert "Traceback" in logs[0].read_text() and "ZeroDivisionError" in logs[0].read_text()
    assert main(["ok", "--n", "x"]) == EXIT_USER and "invalid int" in capsys.readouterr().err


def test_numerical_warnings_go_to_a_log_file_not_the_terminal(run_python, tmp_path):
    """A command whose numpy arithmetic divides by zero or subtracts infinities (as calibration did on pixels
    outside the surface) prints no RuntimeWarning on the terminal: the warnings go to a log file in PROCAM_LOG_DIR;
    other warnings still reach the terminal."""
    logs = tmp_path / "logs"
    done = run_python("""
        import sys
        import warnings

        import numpy as np
        from procam.addon.cli import app

        def noisy(args):
            print(np.array([1.0, 0.0]) / np.array([0.0, 0.0]), np.array([np.inf]) - np.array([np.inf]))
            warnings.warn("a warning meant for the user")
            return 0

        app._COMMANDS[:] = [("noisy", "warns", lambda p: None, noisy)]
        sys.exit(app.main(["noisy"]))
        """, env={"PROCAM_LOG_DIR": str(logs)}, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "RuntimeWarning" not in done.stderr and "encountered" not in done.stderr, done.stderr
    assert "a warning meant for the user" in done.stderr
    written = "".join(p.read_text() for p in logs.glob("procam-noisy-*.log"))
    assert "divide by zero encountered" in written and "invalid value encountered in subtract" in written


def test_cancel_on_interrupt_in_process():
    before = signal.getsignal(signal.SIGINT)  # Python's default, or SIG_IGN when started in the background
    with terminal.cancel_on_interrupt() as cancel:
        assert not cancel()
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
        assert cancel()
        with pytest.raises(KeyboardInterrupt):  # a second Ctrl-C stops at once
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.5)
    assert signal.getsignal(signal.SIGINT) is before  # the handler it found is back


def test_ctrl_c_in_a_real_process_exits_130_without_traceback():
    script = textwrap.dedent("""
        import sys, time
        from procam.addon.cli import app as cli, terminal
        from procam.addon.errors import Cancelled

        def work(args):
            with terminal.cancel_on_interrupt() as cancel:
                print("ready", flush=True)
                for _ in range(400):
                    if cancel():
                        raise Cancelled("stopped between two steps; finished work kept")
                    time.sleep(0.025)
            return 0

        cli._COMMANDS[:] = [("work", "a long job", lambda p: None, work)]
        sys.exit(cli.main(["work"]))
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    assert proc.stdout.readline().strip() == "ready"
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == EXIT_CANCELLED, err
    assert "cancelled: stopped between two steps" in err and "Traceback" not in err


def test_console_script_exit_codes(tmp_path):
    exe = os.path.join(os.path.dirname(sys.executable), "procam")
    if not os.path.exists(exe):
        pytest.skip("the procam console script is not installed in this environment")
    ok = subprocess.run([exe, "--help"], capture_output=True, text=True, timeout=120)
    assert ok.returncode == EXIT_OK and "exit codes:" in ok.stdout
    bad = subprocess.run([exe, "show", str(tmp_path), str(tmp_path / "f_####.png"), "--out", str(tmp_path / "o")],
                         capture_output=True, text=True, timeout=120)
    assert (bad.returncode == EXIT_USER and bad.stderr.startswith("procam show: error:")
            and "Traceback" not in bad.stderr)


def test_the_package_runs_as_a_module_with_the_commands_exit_codes(tmp_path):
    """``python -m procam.addon.cli`` is the procam command (a checkout on the path, not installed)."""
    ok = subprocess.run([sys.executable, "-m", "procam.addon.cli", "--help"], capture_output=True, text=True,
                        timeout=120)
    assert ok.returncode == EXIT_OK and "exit codes:" in ok.stdout
    bad = subprocess.run([sys.executable, "-m", "procam.addon.cli", "evaluate", str(tmp_path / "none"), "--inputs",
                          str(tmp_path), "--targets", "t.png", "--device", "lab:x", "--out", str(tmp_path / "o")],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == EXIT_USER and "Traceback" not in bad.stderr and bad.stderr.startswith("procam")


# -- progress on stderr --------------------------------------------------------------------------

class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_lines_when_not_a_terminal():
    log = io.StringIO()
    bar = ProgressBar(4, "show", unit="frames", stream=log, interval=3600)
    bar.update(0, "frame 1")
    bar.update(0.5, "iteration 10/20")  # throttled: within the interval
    bar.update(0.999, "almost")  # throttled too, and would not say 1 frame done
    bar.update(1, "frame 1 done", force=True)
    bar.close()  # same state as the last forced line: not repeated
    lines = log.getvalue().splitlines()
    assert len(lines) == 2 and "\r" not in log.getvalue()
    assert lines[0].startswith("[procam ") and "show   0% 0/4 frames" in lines[0] and lines[0].endswith("frame 1")
    assert "show  25% 1/4 frames" in lines[1] and "frame 1 done" in lines[1]


def test_progress_bar_on_a_terminal(capsys):
    tty = _Tty()
    bar = ProgressBar(2, "show", unit="frames", stream=tty, interval=0)
    bar.update(0.5, "frame 1: iteration 5/10")
    bar.update(1.0, "frame 1 done")
    bar.close()
    text = tty.getvalue()
    assert text.count("\r") == 3 and text.endswith("\n") and text.count("\n") == 1
    assert "|##########..........| 1/2 frames" in text and "0.5/2 frames" in text
    # A plain progress line while a bar is drawn on stderr: the bar is cleared, the line printed, the bar redrawn.
    with ProgressBar(3, "x", tty=True) as live:
        live.update(1, "one")
        progress("a note")
    err = capsys.readouterr().err
    assert "a note\n" in err and err.rindex("1/3") > err.index("a note")
