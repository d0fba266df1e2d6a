"""Photographs taken by a command: any stills camera (gphoto2, a phone app's tool, a rig's own software) as a device.

Two devices use it:

* ``live:display=N,shoot='gphoto2 --capture-image-and-download --filename {out}'`` (``live/shoot.py``): ProCam shows
  the frame in the projector window, waits for the display to settle, then runs the command;
* ``command:run='my-rig-tool show {frame} --photo {out}'`` (:class:`CommandDevice` here): ProCam writes the frame as
  a 16-bit PNG to ``{frame}`` and the command both shows it and photographs it (rigs driven by other software).
  Several projectors: ``{frame1}`` … ``{frameN}``, one per projector (``{frame}`` is ``{frame1}``).

The command line is split like a shell would split it (``shlex``) and run without a shell: each placeholder is
replaced inside its argument, so a path never goes through a shell's parsing. ``{out}`` is a new path in a private
temporary folder for every shot (never a file that existed before the command ran: a photograph read is one this run
of the command wrote; ``suffix=png`` and so on for another file type than ``.jpg``), ``{n}`` the shot's number
from 0. A photograph is read as ``procam import-captures`` reads
one (:func:`.photos.load_capture`: complete-file check, EXIF orientation; ``encoding=auto`` takes 8-bit files as
sRGB and linearises them, 16-bit and float as linear). RAW files are not read: set the camera to JPEG (or convert,
e.g. ``dcraw -T -4`` gives a linear 16-bit TIFF).

Exposure: when the device opens it takes black, white, and white again :data:`~..live.device.ADAPT_S` seconds later;
a camera that does not see the projector, or whose exposure or white balance moved between the two whites, is
refused (as the live device refuses a camera on auto). Every photograph's EXIF exposure (time, aperture, ISO,
exposure bias, white-balance mode) is compared with the first one's; a photograph whose settings changed is refused
by name. Photographs without EXIF (PNG, TIFF from a tool) are checked at open only.
"""

from __future__ import annotations

import re
import shlex
import shutil
import struct
import subprocess
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
import numpy as np

from ..errors import CaptureError, ImageError
from ..imageio import exif_block, write_image
from ..progress import Progress, quiet
from ..rig.model import Projector
from .devices import ShownTogether
from .exposure import ADAPT_S, COLOUR_TOLERANCE, GAIN_TOLERANCE, SEEN_STEP
from .photos import load_capture

#: Seconds a shot may take when the spec gives no ``timeout=`` (a DSLR over USB takes 1–3 s; autofocus more).
DEFAULT_TIMEOUT = 60.0
#: How much of a failed command's standard error a message quotes.
STDERR_TAIL = 600
#: EXIF tags that fix a photograph's exposure and colour: any change between two shots is a changed exposure.
EXPOSURE_TAGS = {0x829A: "exposure time", 0x829D: "aperture", 0x8827: "ISO", 0x9204: "exposure bias",
                 0xA402: "exposure mode", 0xA403: "white balance mode"}
ENCODINGS = ("auto", "srgb", "linear")
#: What ``{out}`` may end with (``suffix=``): the photograph's file type, for tools that choose it by the name.
SUFFIXES = ("jpg", "jpeg", "png", "tif", "tiff", "exr")


def check_suffix(suffix: str, what: str, error: type[CaptureError] = CaptureError) -> str:
    """``suffix`` (without its dot, lower case) if ``{out}`` may end with it."""
    s = suffix.lower().lstrip(".")
    if s not in SUFFIXES:
        raise error(f"{what}: suffix must be one of {', '.join(SUFFIXES)} (the photograph's file type), got "
                    f"{suffix!r}")
    return s


def split_spec(text: str, prefix: str, known: Sequence[str], form: str, *,
               error: type[CaptureError] = CaptureError) -> dict[str, str]:
    """``key=value,…`` after ``prefix`` (``live:``, ``command:``): a value may be quoted ('…' or "…", commas kept,
    quotes taken off), and an unquoted value runs on over commas until the next ``known`` key (URLs and command
    lines hold commas). ``form`` is the spec's usual form, for the message of a spec that is not one."""
    body = text[len(prefix):] if text.startswith(prefix) else text
    what = prefix.rstrip(":")
    values: dict[str, str] = {}
    last: str | None = None
    quote: str | None = None
    for token in body.split(","):
        if quote is not None:  # inside a quoted value: the comma belongs to it
            assert last is not None
            values[last] += "," + token
            if token.rstrip().endswith(quote):
                quote = None
            continue
        key, eq, value = token.partition("=")
        if eq and key.strip() in known:
            last = key.strip()
            if last in values:
                raise error(f"{what} device: {last} is given twice in {text!r}")
            value = value.strip()
            if value[:1] in ("'", '"') and not (len(value) > 1 and value.endswith(value[0])):
                quote = value[0]
            values[last] = value
        elif last is not None:  # a comma inside the previous value
            values[last] += "," + token
        else:
            raise error(f"{what} device: expected key=value, got {token!r} in {text!r}; the form is {form}")
    if quote is not None:
        raise error(f"{what} device: a quote ({quote}) is not closed in {text!r}")
    for key, value in values.items():
        value = value.strip()
        if len(value) > 1 and value[0] in ("'", '"') and value.endswith(value[0]):
            values[key] = value[1:-1]
    return values


def parse_command(line: str, what: str, needs: Sequence[str] = ("{out}",), *,
                  error: type[CaptureError] = CaptureError) -> tuple[str, ...]:
    """A command line split into arguments (``shlex``, no shell), with each of ``needs`` in one of them."""
    try:
        argv = tuple(shlex.split(line))
    except ValueError as exc:
        raise error(f"{what}: cannot split the command {line!r} into arguments ({exc})") from None
    if not argv:
        raise error(f"{what}: the command is empty")
    missing = [n for n in needs if not any(n in a for a in argv)]
    if missing:
        raise error(f"{what}: the command {line!r} must name {' and '.join(missing)} (where "
                           f"{'it writes the photograph' if missing == ['{out}'] else 'ProCam puts the file'}), e.g. "
                           "gphoto2 --capture-image-and-download --filename {out}")
    return argv


def exif_exposure(path: str | Path) -> dict[str, float]:
    """The exposure-deciding EXIF values (:data:`EXPOSURE_TAGS`) of a JPEG or TIFF; {} when it has none."""
    tiff = exif_block(path)
    if tiff is None or len(tiff) < 8 or tiff[:2] not in (b"II", b"MM"):
        return {}
    e = "<" if tiff[:2] == b"II" else ">"
    found: dict[str, float] = {}
    sizes = {1: 1, 3: 2, 4: 4, 5: 8, 9: 4, 10: 8}

    def value(typ: int, at: int) -> float | None:
        try:
            if typ == 3:
                return float(struct.unpack(e + "H", tiff[at:at + 2])[0])
            if typ in (4, 9):
                return float(struct.unpack(e + ("I" if typ == 4 else "i"), tiff[at:at + 4])[0])
            if typ in (5, 10):
                num, den = struct.unpack(e + ("II" if typ == 5 else "ii"), tiff[at:at + 8])
                return num / den if den else None
            if typ == 1:
                return float(tiff[at])
        except (struct.error, IndexError):
            return None
        return None

    def walk(ifd: int, depth: int) -> None:
        if depth > 2 or ifd + 2 > len(tiff):
            return
        (n,) = struct.unpack(e + "H", tiff[ifd:ifd + 2])
        for i in range(min(n, 512)):
            at = ifd + 2 + 12 * i
            if at + 12 > len(tiff):
                return
            tag, typ, count = struct.unpack(e + "HHI", tiff[at:at + 8])
            if tag == 0x8769 and typ in (4, 13):  # the Exif sub-IFD
                walk(struct.unpack(e + "I", tiff[at + 8:at + 12])[0], depth + 1)
            elif tag in EXPOSURE_TAGS and typ in sizes and count >= 1:
                where = at + 8 if sizes[typ] <= 4 else struct.unpack(e + "I", tiff[at + 8:at + 12])[0]
                v = value(typ, where)
                if v is not None:
                    found[EXPOSURE_TAGS[tag]] = v

    walk(struct.unpack(e + "I", tiff[4:8])[0], 0)
    return found


class PhotoCommand:
    """A command that writes one photograph to ``{out}``: run, waited for, its photograph read (linear float32).

    ``argv``: the command's arguments with placeholders; :meth:`take` replaces ``{out}`` (a new path in the
    private folder), ``{n}`` (the shot's number) and the ones it is given. Close it to remove the folder."""

    def __init__(self, argv: Sequence[str], *, timeout: float = DEFAULT_TIMEOUT, encoding: str = "auto",
                 suffix: str = "jpg", what: str = "the shooting command") -> None:
        if encoding not in ENCODINGS:
            raise CaptureError(f"{what}: encoding must be one of {', '.join(ENCODINGS)}, got {encoding!r}")
        self.argv, self.timeout, self.encoding, self.what = tuple(argv), float(timeout), encoding, what
        self.suffix = "." + check_suffix(suffix, what)
        self.folder = Path(tempfile.mkdtemp(prefix="procam-shots-"))
        self.shots = 0
        self.first_exif: dict[str, float] | None = None
        self.first_name = ""
        self.seconds: list[float] = []

    def path(self, name: str) -> Path:
        """A path in the private folder (for files the device hands to the command)."""
        return self.folder / name

    def take(self, substitutions: Mapping[str, str] | None = None) -> np.ndarray:
        """Run the command once and return its photograph (float32 H×W×3, linear)."""
        n = self.shots
        self.shots += 1
        out = self.folder / f"shot-{n:05d}{self.suffix}"
        for stale in self.folder.glob(f"shot-{n:05d}*"):
            stale.unlink()
        subs = {"{out}": str(out), "{n}": str(n), **(substitutions or {})}
        argv = [self._substitute(a, subs) for a in self.argv]
        start = time.perf_counter()
        try:
            done = subprocess.run(argv, stdin=subprocess.DEVNULL, capture_output=True,
                                  timeout=self.timeout)
        except FileNotFoundError:
            raise CaptureError(f"{self.what}: {argv[0]!r} was not found; install it or give its full path") from None
        except PermissionError:
            raise CaptureError(f"{self.what}: {argv[0]!r} cannot be run (no permission to execute it)") from None
        except subprocess.TimeoutExpired as exc:
            raise CaptureError(f"{self.what} took more than {self.timeout:g} s and was stopped{_tail(exc.stderr)}; "
                               "check the camera (connected, awake, not busy), or give a longer timeout=SECONDS"
                               ) from None
        self.seconds.append(time.perf_counter() - start)
        if done.returncode != 0:
            raise CaptureError(f"{self.what} failed (exit status {done.returncode}): {shlex.join(argv)}"
                               f"{_tail(done.stderr)}")
        found = out if out.is_file() else self._written_instead(n)
        if found is None:
            raise CaptureError(f"{self.what} ran but wrote no photograph to {out}: the command must save the "
                               f"photograph at the path that replaces {{out}}{_tail(done.stderr)}")
        try:
            image, _ = load_capture(found, self.encoding)
        except (CaptureError, ImageError) as exc:
            raise CaptureError(f"{self.what} wrote a photograph that cannot be read: {exc}. ProCam reads JPEG, PNG, "
                               "TIFF and EXR (not RAW: set the camera to JPEG)") from None
        self._check_exif(found, n)
        found.unlink(missing_ok=True)
        return image

    def _written_instead(self, n: int) -> Path | None:
        # Tools that add their own suffix (gphoto2's %C, a phone app) write shot-NNNNN.<their suffix>.
        written = [p for p in self.folder.glob(f"shot-{n:05d}*") if p.is_file()]
        return written[0] if len(written) == 1 else None

    @staticmethod
    def _substitute(arg: str, subs: Mapping[str, str]) -> str:
        for key, value in subs.items():
            arg = arg.replace(key, value)
        return arg

    def _check_exif(self, path: Path, n: int) -> None:
        exif = exif_exposure(path)
        if self.first_exif is None:
            self.first_exif, self.first_name = exif, f"shot {n}"
            return
        changed = [f"{k} {self.first_exif[k]:g} → {exif[k]:g}" for k in self.first_exif
                   if k in exif and not np.isclose(exif[k], self.first_exif[k], rtol=1e-4)]
        if changed:
            raise CaptureError(f"photograph {n} was taken with other exposure settings than the first "
                               f"({', '.join(changed)}): the camera is on auto. Set manual exposure, a fixed ISO and "
                               "a fixed white balance on the camera, then start again")

    def close(self) -> None:
        """Remove the private folder and whatever is left in it."""
        shutil.rmtree(self.folder, ignore_errors=True)


def _tail(stderr: bytes | str | None) -> str:
    if not stderr:
        return ""
    text = stderr.decode(errors="replace") if isinstance(stderr, bytes) else stderr
    text = text.strip()
    return f"; its error output ends: {text[-STDERR_TAIL:]}" if text else ""


@dataclass(frozen=True)
class ShotReport:
    """What a device of photographs measured when it opened (:func:`check_shots`)."""

    latency_s: float | None  # None: the command shows the frame itself
    seconds_per_shot: float
    contrast: float
    noise: float
    average: int
    exposure_drift: float
    colour_drift: float

    def lines(self) -> list[str]:
        settle = "" if self.latency_s is None else f"display settle {self.latency_s * 1000:.0f} ms before each shot; "
        return [f"{settle}{self.seconds_per_shot:.2f} s a photograph; {self.average} photograph(s) averaged per "
                "capture",
                f"white − black {self.contrast:.3f}; noise {self.noise:.4f} per photograph; white drift between two "
                f"photographs: exposure {self.exposure_drift * 100:.1f} %, colour {self.colour_drift * 100:.1f} %"]

    def to_dict(self) -> dict[str, object]:
        return {"latency_s": self.latency_s, "seconds_per_shot": self.seconds_per_shot, "contrast": self.contrast,
                "noise_per_frame": self.noise, "average": self.average, "exposure_drift": self.exposure_drift,
                "colour_drift": self.colour_drift}


def check_shots(capture: Callable[[float], np.ndarray], *, check_exposure: bool, adapt_s: float,
                say: Progress) -> tuple[np.ndarray, float, float, float, float]:
    """Black, white, and white again ``adapt_s`` later through ``capture(level)``; refuse a camera that does not see
    the projector or whose exposure moved. Returns the first white, white − black, the per-photograph noise and the
    exposure and colour drifts."""
    say("photographing black and white: does the camera see the projector?", 0.2)
    black = capture(0.0)
    white = capture(1.0)
    contrast = float(np.mean(white) - np.mean(black))
    if contrast < SEEN_STEP:
        raise CaptureError(f"the camera did not see the projector: a full white frame raised the photograph's mean by "
                           f"{contrast * 100:.1f} % (less than {SEEN_STEP * 100:.0f} %). Point the camera at the "
                           "projected image, check that the projector shows the window, and open the lens")
    if not check_exposure:
        return white, contrast, 0.0, 0.0, 0.0
    say("checking that the camera's exposure and white balance are locked", 0.6)
    time.sleep(adapt_s)
    again = capture(1.0)
    lit = white.mean(axis=2) > 0.05 * max(float(white.mean(axis=2).max()), 1e-6)
    noise = float(np.median(np.abs(again - white))) * 1.4826 / np.sqrt(2.0)  # robust σ of one photograph
    if lit.sum() < 16:
        return white, contrast, noise, 0.0, 0.0
    a = white[lit].mean(axis=0).astype(np.float64) + 1e-6
    b = again[lit].mean(axis=0).astype(np.float64) + 1e-6
    ratio = np.log(b / a)
    drift = float(abs(ratio.mean())), float(np.max(np.abs(ratio - ratio.mean())))
    if drift[0] > GAIN_TOLERANCE or drift[1] > COLOUR_TOLERANCE:
        what = "exposure" if drift[0] > GAIN_TOLERANCE else "white balance"
        raise CaptureError(f"the camera's {what} is not locked: two photographs of the same white frame differ by "
                           f"{max(drift) * 100:.0f} %. Switch the camera to manual exposure, a fixed ISO and a fixed "
                           "white balance, then start again")
    return white, contrast, noise, *drift


@dataclass(frozen=True)
class CommandSpec:
    """What ``command:run='…'[,timeout=SECONDS][,encoding=auto|srgb|linear][,suffix=jpg|png|…][,average=N]`` asks
    for."""

    argv: tuple[str, ...]
    timeout: float = DEFAULT_TIMEOUT
    encoding: str = "auto"
    average: int = 1
    suffix: str = "jpg"

    FORM = "command:run='TOOL … {frame} … {out}' (the frame ProCam writes, the photograph the tool writes)"

    @staticmethod
    def parse(text: str) -> CommandSpec:
        values = split_spec(text, "command:", ("run", "timeout", "encoding", "average", "suffix"), CommandSpec.FORM)
        if "run" not in values:
            raise CaptureError(f"command device: say which command shows and photographs a frame, {CommandSpec.FORM}"
                               f"; got {text!r}")
        argv = parse_command(values["run"], "command device", ("{out}",))
        if not any("{frame" in a for a in argv):
            raise CaptureError(f"command device: the command {values['run']!r} must name {{frame}} (the 16-bit PNG of "
                               "the frame to show); several projectors: {frame1} … {frameN}")
        try:
            timeout = float(values.get("timeout", DEFAULT_TIMEOUT))
            average = int(values.get("average", 1))
        except ValueError as exc:
            raise CaptureError(f"command device: a value in {text!r} is not a number ({exc})") from None
        if not 0 < timeout <= 3600:
            raise CaptureError(f"command device: timeout must be 0 … 3600 s, got {timeout:g}")
        if not 1 <= average <= 64:
            raise CaptureError(f"command device: average must be 1 … 64 photographs, got {average}")
        encoding = values.get("encoding", "auto")
        if encoding not in ENCODINGS:
            raise CaptureError(f"command device: encoding must be auto, srgb or linear, got {encoding!r}")
        suffix = check_suffix(values.get("suffix", "jpg"), "command device")
        return CommandSpec(argv, timeout, encoding, average, suffix)

    def check_projectors(self, count: int) -> None:
        """Refuse, before anything runs, a command that does not name one frame file per projector."""
        names = {f"{{frame{k + 1}}}" for k in range(count)}
        given = {"{frame1}" if m == "{frame}" else m for a in self.argv for m in _frame_names(a)}
        if count == 1:
            if "{frame1}" not in given:
                raise CaptureError("command device: the command must name {frame}")
            return
        missing = sorted(names - given)
        if missing:
            raise CaptureError(f"command device: this rig has {count} projectors; the command must name one frame "
                               f"file each, {{frame1}} … {{frame{count}}} (missing {', '.join(missing)})")


def _frame_names(arg: str) -> list[str]:
    return re.findall(r"\{frame\d*\}", arg)


class CommandDevice(ShownTogether):
    """``command:run=…``: a command shows each frame (a 16-bit PNG ProCam writes) and photographs it."""

    what = "this command device"

    def __init__(self, spec: CommandSpec | str, projector: Projector, *, others: Sequence[Projector] = (),
                 progress: Progress | None = None, check_exposure: bool = True) -> None:
        say = progress or quiet
        self.spec = spec if isinstance(spec, CommandSpec) else CommandSpec.parse(spec)
        self.projector, self.others = projector, tuple(others)
        self.spec.check_projectors(len(self.projectors))
        self._command = PhotoCommand(self.spec.argv, timeout=self.spec.timeout, encoding=self.spec.encoding,
                                     suffix=self.spec.suffix, what="the command device's command")
        try:
            white, contrast, noise, *drift = check_shots(lambda v: self._capture(self._flat(v)),
                                                         check_exposure=check_exposure, adapt_s=ADAPT_S, say=say)
            seconds = float(np.median(self._command.seconds)) if self._command.seconds else 0.0
            self.report = ShotReport(None, seconds, contrast, noise, self.spec.average, *drift)
        except BaseException:
            self.close()
            raise

    def _capture(self, frames: Sequence[np.ndarray]) -> np.ndarray:
        if self._command is None:
            raise CaptureError("the command device is closed")
        n = self._command.shots
        subs: dict[str, str] = {}
        for k, frame in enumerate(frames):
            # A new file per shot: a command that failed to read it never sees the previous frame instead.
            path = write_image(self._command.path(f"frame-{n:05d}-p{k + 1}.png"), frame)
            subs[f"{{frame{k + 1}}}"] = str(path)
            if k == 0:
                subs["{frame}"] = str(path)
        shots = [self._command.take(subs) for _ in range(self.spec.average)]
        for path in set(subs.values()):
            Path(path).unlink(missing_ok=True)
        image = np.mean(shots, axis=0).astype(np.float32) if len(shots) > 1 else shots[0]
        return self._same_size(image, self._command.shots - 1)

    def close(self) -> None:
        command, self._command = getattr(self, "_command", None), None
        if command is not None:
            command.close()


__all__ = ["CommandDevice", "CommandSpec", "PhotoCommand", "ShotReport", "check_shots", "exif_exposure",
           "parse_command", "split_spec"]
