"""The report's page: one HTML file from the Jinja2 template ``templates/report.html.j2`` beside this module.

The page names no external resource (no stylesheet, font, script or image
file): its style is in the page and every picture is a data URI, so the file
can be mailed, archived or opened offline and shows the same. Every text from
a folder is escaped (autoescape), so a file or target name cannot inject markup.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

TEMPLATES = Path(__file__).parent / "templates"
TEMPLATE = "report.html.j2"
#: the page's generator tag: a file holding it was written by ``procam report`` and may be replaced with --force
GENERATOR = "procam report 1"


def render(context: dict[str, Any]) -> str:
    """The report's HTML for ``context`` (the keys the template reads: title, generator, facts, sections,
    skipped)."""
    import jinja2  # on first use: Blender lacks it, and imports the engine without building a report

    env = jinja2.Environment(loader=jinja2.FileSystemLoader(str(TEMPLATES)),
                             autoescape=jinja2.select_autoescape(("html", "j2")), undefined=jinja2.StrictUndefined,
                             trim_blocks=True, lstrip_blocks=True)
    return env.get_template(TEMPLATE).render(generator=GENERATOR, **context)


def written_by_report(path: str | Path) -> bool:
    """Whether the file at ``path`` is a page this module wrote (its generator tag in the first kilobytes)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096)
    except OSError:
        return False
    return f'<meta name="generator" content="{GENERATOR}">'.encode() in head
