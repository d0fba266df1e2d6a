"""The report step: one self-contained HTML page of step folders, or of a whole tree of them (``procam report``).

Given folders, it walks each (a step folder, or any folder holding step folders, a
demo's for example) and recognises step folders by their manifest and format tag
(:mod:`.layout`). Each recognised folder becomes a section of the page
(:mod:`.report_sections` reads it); the pictures are drawn by
:mod:`..report.figures` and the page by :mod:`..report.page`. What cannot be
shown — a folder that is not ProCam's, a manifest of another format version or
one missing what this version records, an image missing inside a folder — is
listed on the page under *Skipped* with the reason, and the page is written
anyway: a report is for looking, and half a picture with the reason for the
other half beats none.

The page is written under a temporary name and renamed into place; an existing
file is replaced only with ``force`` and only if a report wrote it. The
folders read are never written into, except the top of a demo folder, whose
own ``report.html`` it is.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import ProCamError
from ..imageio import write_atomic_bytes
from ..options import option, validate
from ..outputs import check_file_replaceable, writer_lock
from ..progress import Cancel, Progress, check, quiet
from ..report import figures, page
from . import layout, report_sections

#: the report's file name where a step writes one beside its folders (the demo's)
REPORT_HTML = "report.html"
#: the kinds that become sections, in the page's order; capture sets, pattern sequences and frame sequences are
#: recognised (and read by the sections that use them) but have no section of their own
SHOWN = (layout.DEMO, layout.CALIBRATION, layout.COMPENSATION, layout.EVALUATION, layout.DIAGNOSIS, layout.SHOW)
#: how deep below a folder given the walk looks for step folders
MAX_DEPTH = 4


class ReportError(ProCamError):
    """A report that cannot be written (its output file), or given nothing to read."""


@dataclass(frozen=True)
class ReportOptions:
    """What ``procam report`` asks for."""

    folders: tuple[Path, ...]
    out: Path = option(Path("report.html"), metavar="FILE",
                       help="the HTML file to write (default report.html)")
    title: str = option("", help="the page's title (default: the folders' names)")
    thumbnails: int = option(24, min=1, max=200,
                             help="a show's frames shown as thumbnails at most, evenly spaced (default 24)")
    force: bool = option(False, help="replace an existing report file (only one a report wrote)")


@dataclass
class Found:
    """A step folder the walk recognised: its kind, place and manifest document."""

    kind: layout.FolderKind
    path: Path
    doc: dict[str, Any]


@dataclass
class Walk:
    """What the walk over the folders given found, and what it skipped with the reason."""

    found: list[Found] = field(default_factory=list)
    skipped: list[tuple[str, str]] = field(default_factory=list)

    def skip(self, path: str | Path, reason: str) -> None:
        self.skipped.append((str(path), reason))


def _recognise(folder: Path, walk: Walk) -> Found | None | bool:
    """The step folder ``folder`` is (a :class:`Found`); False when it holds no manifest; None when it holds one
    that cannot be read as its kind (skipped, with the reason)."""
    for kind in layout.FOLDER_KINDS:
        manifest = folder / kind.manifest
        if not manifest.is_file():
            continue
        try:
            doc = json.loads(manifest.read_text())
        except (OSError, ValueError) as exc:
            walk.skip(folder, f"its {kind.manifest} cannot be read ({exc}); is it damaged?")
            return None
        if not isinstance(doc, dict) or doc.get("format") != kind.format:
            continue  # a file of that name another tool wrote: maybe another kind's manifest is here
        version = doc.get("version")
        if version != kind.version:
            walk.skip(folder, f"a {kind.what} of format version {version!r}, written by another version of ProCam; "
                              f"this one reads version {kind.version}: remake it with {kind.made_by}")
            return None
        return Found(kind, folder, doc)
    return False


def _walk(folder: Path, walk: Walk, depth: int) -> int:
    """Recognise ``folder`` and look inside it (a demo folder, or a folder that is none); step folders found."""
    found = _recognise(folder, walk)
    if found is None:
        return 1  # a step folder, though one that cannot be shown: the reason is listed already
    n = 0
    if found:
        walk.found.append(found)
        n = 1
        if found.kind is not layout.DEMO:
            return n  # a step folder's own subfolders (diagnostics, per-projector parts) are its section's
    if depth >= MAX_DEPTH:
        return n
    try:
        subs = sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")
                      and not p.is_symlink())
    except OSError as exc:
        walk.skip(folder, f"cannot look inside ({exc.strerror or exc})")
        return n
    for sub in subs:
        n += _walk(sub, walk, depth + 1)
    return n


def find_folders(folders: tuple[Path, ...] | list[Path]) -> Walk:
    """Walk ``folders``: the step folders in them (each once) and what was skipped and why."""
    walk = Walk()
    for root in folders:
        root = Path(root)
        if not root.exists():
            walk.skip(root, "does not exist")
        elif not root.is_dir():
            walk.skip(root, "is a file, not a folder; give a step folder or a folder holding step folders")
        elif _walk(root, walk, 0) == 0:
            names = ", ".join(k.manifest for k in SHOWN)
            walk.skip(root, f"not a ProCam step folder: holds no {names} (nor a step folder inside, "
                            f"{MAX_DEPTH} levels deep)")
    seen: set[str] = set()
    unique = []
    for f in walk.found:
        key = os.path.realpath(f.path)
        if key not in seen:
            seen.add(key)
            unique.append(f)
    walk.found = unique
    return walk


@dataclass
class ReportResult:
    """The page written: its path, size, the seconds it took, the sections shown and what was skipped."""

    path: Path
    bytes: int
    seconds: float
    sections: list[str]
    skipped: list[tuple[str, str]]


def _inputs_to_protect(walk: Walk) -> list[Path]:
    """The folders a report must not write into: every step folder read but a demo's, whose top holds its own
    report."""
    return [f.path for f in walk.found if f.kind is not layout.DEMO]


def build(options: ReportOptions, progress: Progress | None = None, cancel: Cancel | None = None) -> tuple[str, Walk]:
    """The page's HTML for ``options.folders`` and the walk it was made from (nothing written)."""
    say = progress or quiet
    if not options.folders:
        raise ReportError("give at least one folder to report on")
    say("looking for step folders", 0.0)
    walk = find_folders(options.folders)
    shown = sorted((f for f in walk.found if f.kind in SHOWN),
                   key=lambda f: (SHOWN.index(f.kind), str(f.path)))
    reader = report_sections.Reader(walk.found, walk.skip, thumbnails=options.thumbnails)
    sections: list[dict[str, Any]] = []
    facts: list[tuple[str, str]] = []
    for i, f in enumerate(shown):
        check(cancel, "the report was cancelled; nothing was written")
        say(f"{f.kind.what} {f.path}", 0.05 + 0.9 * i / max(len(shown), 1))
        try:
            section = reader.section(f)
        except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
            walk.skip(f.path, f"its {f.kind.manifest} lacks what this version of ProCam records ({type(exc).__name__}: "
                              f"{exc}); it was written by an older version: remake it with {f.kind.made_by}")
            continue
        except ProCamError as exc:
            walk.skip(f.path, str(exc))
            continue
        if f.kind is layout.DEMO:
            facts = section["facts"]
            continue
        section["id"] = f"s{len(sections) + 1}"
        sections.append(section)
    titles = [s["title"] for s in sections]
    for s in sections:  # two folders of one kind (a compensation with effects beside one without): name them
        if titles.count(s["title"]) > 1:
            s["title"] = f"{s['title']} — {Path(s['folder']).name}"
    names = ", ".join(Path(p).name or str(p) for p in options.folders)
    context = {"title": options.title or f"ProCam report — {names}",
               "subtitle": f"{len(sections)} section(s) from {', '.join(str(p) for p in options.folders)}; "
                           f"made {time.strftime('%Y-%m-%d %H:%M')}",
               "facts": facts, "sections": sections,
               "skipped": [{"path": p, "reason": r} for p, r in walk.skipped],
               "footer": "Made by procam report. Pictures of light (captures, targets, frames) are shown "
                         "sRGB-encoded from the folders' linear images; maps show numbers on the colour scale beside "
                         "them."}
    return page.render(context), walk


def place_for(folders: list[Path] | tuple[Path, ...]) -> Path:
    """Where the sidebar's report of ``folders`` goes: ``report.html`` in the folder that holds them all (their
    common parent; a demo's own report when they are a demo's folders)."""
    if not folders:
        raise ReportError("no step folder to report on: run a step, or choose its folder in the ProCam panel")
    parents = [os.path.abspath(Path(f).parent) for f in folders]
    try:
        common = Path(os.path.commonpath(parents))
    except ValueError:  # folders on different drives: beside the first
        common = Path(parents[0])
    return common / REPORT_HTML


def missing_libraries() -> list[str]:
    """What building a report needs that this Python lacks (Blender has neither matplotlib nor Jinja2)."""
    import importlib.util

    return figures.missing_libraries() + (["Jinja2"] if importlib.util.find_spec("jinja2") is None else [])


def run(options: ReportOptions, progress: Progress | None = None, cancel: Cancel | None = None) -> ReportResult:
    """Write the report of ``options.folders`` to ``options.out`` (module doc)."""
    validate(options, ReportError)
    missing = missing_libraries()
    if missing:
        raise ReportError(f"building a report needs {' and '.join(missing)}, which this Python lacks (Blender does "
                          "not ship them): run `procam report FOLDER --out report.html` from ProCam's environment "
                          "(scripts/setup.sh installs them)")
    t0 = time.perf_counter()
    out = Path(options.out)
    if out.suffix.lower() not in (".html", ".htm"):
        raise ReportError(f"the report {out} must be an .html file; give a name ending in .html")
    walk = find_folders(options.folders)
    # checked before the work (a refusal costs nothing) and again before writing (it may have appeared since)
    check_file_replaceable(out, force=options.force, what="ProCam report", replaceable=page.written_by_report,
                           inputs=_inputs_to_protect(walk), error=ReportError)
    with writer_lock(out):  # another run writing this report is refused before any work
        return _write(options, out, progress, cancel, t0)


def _write(options: ReportOptions, out: Path, progress: Progress | None, cancel: Cancel | None,
           t0: float) -> ReportResult:
    say = progress or quiet
    html, walk = build(options, progress, cancel)
    check(cancel, "the report was cancelled; nothing was written")
    check_file_replaceable(out, force=options.force, what="ProCam report", replaceable=page.written_by_report,
                           inputs=_inputs_to_protect(walk), error=ReportError)
    data = html.encode("utf-8")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ReportError(f"cannot write the report {out}: {exc.strerror or exc}") from None
    write_atomic_bytes(out, data)
    say("done", 1.0)
    return ReportResult(out, len(data), time.perf_counter() - t0,
                        [str(f.path) for f in walk.found if f.kind in SHOWN], walk.skipped)
