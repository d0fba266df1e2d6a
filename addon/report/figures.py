"""The report's pictures: images and plots as embedded PNG data (``data:image/png;base64,…``), drawn with matplotlib.

Everything here takes plain arrays and numbers — no step folder is read here
(the report step, ``steps/report.py``, reads them) — and returns a data URI
that an ``<img>`` shows without any file beside the page. matplotlib draws on
its Agg canvas (no display, no window), one figure at a time, closed at once;
it is imported on first use, so the engine (and Blender, which lacks it)
imports this module without it.

Images in the folders are linear light (DESIGN.md §3); a picture of light a
person looks at (a capture, a target, a projector frame) is sRGB-encoded here
for the screen, and says so in its caption. Maps of numbers (an error, a
residual) are drawn with a colour scale beside them instead.
"""

from __future__ import annotations

import base64
import importlib.util
import io
import textwrap
from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np

from ..colour import srgb_encode

#: what drawing the plots needs beyond the engine's own dependencies (not bundled into the Blender extension)
LIBRARIES = ("matplotlib",)


def missing_libraries() -> list[str]:
    """The libraries of :data:`LIBRARIES` that this Python cannot import (a Blender without them)."""
    return [name for name in LIBRARIES if importlib.util.find_spec(name) is None]


def _mpl() -> Any:
    """matplotlib on its Agg canvas (no display: the report is built headless, in a terminal or a Blender job),
    imported on first use so that the engine imports without it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.cm
    import matplotlib.colors
    import matplotlib.lines
    import matplotlib.patches
    import matplotlib.pyplot
    import matplotlib.ticker
    return matplotlib


#: pixels per inch of every plot: sharp on a laptop screen without making the page heavy
DPI = 110
#: the colour map of error and residual maps (the diagnosis's own PNG maps use OpenCV's inferno, the same map)
HEAT = "inferno"
#: region outline colours, in rank order (colour-blind-safe, Okabe–Ito)
REGION_COLOURS = ("#E69F00", "#56B4E9", "#009E73", "#F0E442", "#0072B2", "#D55E00", "#CC79A7", "#FFFFFF")


def _uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def image_uri(image: np.ndarray, *, light: bool = True, width: int | None = None) -> str:
    """An H×W×3 (or H×W) image in [0, 1] as a PNG data URI; ``light``: linear light, sRGB-encoded for the screen;
    ``width``: scaled down to at most this many pixels across (thumbnails)."""
    img = np.nan_to_num(np.asarray(image, np.float32))
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    img = srgb_encode(img) if light else np.clip(img, 0.0, 1.0)
    if width is not None and img.shape[1] > width:
        h = max(1, round(img.shape[0] * width / img.shape[1]))
        img = cv2.resize(img, (width, h), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".png", (img[..., ::-1] * 255 + 0.5).astype(np.uint8))
    if not ok:  # OpenCV only fails here on an empty image, which the callers never pass
        raise ValueError("cannot encode an empty image")
    return _uri(buf.tobytes())


def _figure_uri(fig: Any) -> str:
    buf = io.BytesIO()
    try:
        fig.savefig(buf, format="png", dpi=DPI, bbox_inches="tight")
    finally:
        _mpl().pyplot.close(fig)
    return _uri(buf.getvalue())


def _figure(width: float, height: float, ncols: int = 1, **kw: Any) -> tuple[Any, np.ndarray]:
    fig, axes = _mpl().pyplot.subplots(1, ncols, figsize=(width, height), squeeze=False, **kw)
    return fig, axes[0]


def _show(ax: Any, image: np.ndarray, title: str, *, light: bool = True) -> None:
    img = np.nan_to_num(np.asarray(image, np.float32))
    ax.imshow(srgb_encode(img) if light else np.clip(img, 0, 1), interpolation="nearest")
    ax.set_title(title, fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])


def _panel_size(shape: tuple[int, ...], across: float = 2.6) -> tuple[float, float]:
    """Inches of one picture panel ``across`` wide, keeping the image's aspect ratio."""
    return across, across * shape[0] / max(shape[1], 1)


def comparison(target: np.ndarray, uncompensated: np.ndarray, compensated: np.ndarray, captions: Sequence[str],
               scale: float) -> str:
    """Target | uncompensated capture | compensated capture | error map of the compensated capture (mean over
    channels of |capture − target|, linear, 0 … ``scale``), each with its caption, the error's colour scale beside."""
    w, h = _panel_size(target.shape)
    fig, axes = _figure(4 * w + 0.8, h + 0.7, 4)
    for ax, img, cap in zip(axes[:3], (target, uncompensated, compensated), captions):
        _show(ax, img, cap)
    err = np.abs(np.asarray(compensated, np.float32) - np.asarray(target, np.float32)).mean(axis=2)
    im = axes[3].imshow(err, cmap=HEAT, vmin=0.0, vmax=scale, interpolation="nearest")
    axes[3].set_title(captions[3] if len(captions) > 3 else "error", fontsize=9)
    axes[3].set_xticks([])
    axes[3].set_yticks([])
    bar = fig.colorbar(im, ax=axes[3], fraction=0.046, pad=0.04)
    bar.set_label("|capture − target| (linear)", fontsize=8)
    bar.ax.tick_params(labelsize=7)
    return _figure_uri(fig)


def heat_maps(maps: Sequence[np.ndarray], titles: Sequence[str], scale: float, label: str) -> str:
    """Maps of one quantity side by side on one colour scale (0 … ``scale``), the scale beside them. A map is
    H×W values, or H×W×3 already coloured with :data:`HEAT` over 0 … ``scale`` (the diagnosis's PNG maps)."""
    w, h = _panel_size(maps[0].shape, 3.2)
    fig, axes = _figure(len(maps) * w + 0.9, h + 0.6, len(maps))
    for ax, m, title in zip(axes, maps, titles):
        m = np.asarray(m, np.float32)
        if m.ndim == 3:
            ax.imshow(np.clip(m, 0, 1), interpolation="nearest")
        else:
            ax.imshow(m, cmap=HEAT, vmin=0.0, vmax=scale, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    mpl = _mpl()
    mappable = mpl.cm.ScalarMappable(mpl.colors.Normalize(0.0, scale), HEAT)
    bar = fig.colorbar(mappable, ax=list(axes), fraction=0.046 / len(maps) ** 0.5, pad=0.02)
    bar.set_label(label, fontsize=8)
    bar.ax.tick_params(labelsize=7)
    return _figure_uri(fig)


def pictures(images: Sequence[np.ndarray], titles: Sequence[str], *, light: Sequence[bool] | bool = True,
             across: float = 3.0) -> str:
    """Pictures side by side, each with its title."""
    lights = [light] * len(images) if isinstance(light, bool) else list(light)
    w, h = _panel_size(images[0].shape, across)
    fig, axes = _figure(len(images) * w, h + 0.5, len(images))
    for ax, img, title, lit in zip(axes, images, titles, lights):
        _show(ax, img, title, light=lit)
    return _figure_uri(fig)


def coverage(background: np.ndarray, valid: np.ndarray, coords: np.ndarray, size: tuple[int, int]) -> str:
    """Gray-code coverage: where the camera decoded a projector pixel, coloured by the decoded column and row
    (0 … the projector's width and height), over the white capture in grey elsewhere."""
    grey = srgb_encode(np.nan_to_num(np.asarray(background, np.float32)).mean(axis=2))
    w, h = _panel_size(grey.shape, 3.2)
    fig, axes = _figure(2 * w + 1.6, h + 0.6, 2)
    for ax, k, name, top in ((axes[0], 0, "projector column", size[0]), (axes[1], 1, "projector row", size[1])):
        ax.imshow(grey, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        shown = np.where(valid, coords[..., k], np.nan)
        im = ax.imshow(shown, cmap="viridis", vmin=0, vmax=top, interpolation="nearest")
        ax.set_title(f"decoded {name}", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
        bar = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04)
        bar.set_label(f"{name} (px)", fontsize=8)
        bar.ax.tick_params(labelsize=7)
    return _figure_uri(fig)


def warp_field(shifts: np.ndarray, size: tuple[int, int]) -> str:
    """The stage-B warp: its shift at each control point as arrows over its length in input pixels."""
    grid = np.asarray(shifts, np.float64)
    n_y, n_x = grid.shape[:2]
    xs = np.linspace(0, size[0], n_x)
    ys = np.linspace(0, size[1], n_y)
    length = np.hypot(grid[..., 0], grid[..., 1])
    fig, axes = _figure(4.6, 4.6 * size[1] / max(size[0], 1) + 0.5)
    ax = axes[0]
    im = ax.imshow(length, cmap="viridis", extent=(0, size[0], size[1], 0), interpolation="bilinear")
    ax.quiver(*np.meshgrid(xs, ys), grid[..., 0], grid[..., 1], color="white", angles="xy", scale_units="xy",
              scale=max(float(length.max()), 1e-6) / (0.6 * size[0] / max(n_x - 1, 1)))
    ax.set_title("warp shift at each control point (arrows not to scale)", fontsize=9)
    ax.set_xlabel("projector input x (px)", fontsize=8)
    ax.set_ylabel("y (px)", fontsize=8)
    ax.tick_params(labelsize=7)
    bar = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04)
    bar.set_label("shift (input px)", fontsize=8)
    bar.ax.tick_params(labelsize=7)
    return _figure_uri(fig)


def pose_views(projectors: Sequence[np.ndarray], directions: Sequence[np.ndarray], points: np.ndarray | None) -> str:
    """The rig from above (x–z) and from the side (z–y): the camera at the origin looking along +z, each projector
    and its optical axis (numbered when there are several), the surface's vertices."""
    fig, axes = _figure(7.0, 3.2, 2)
    reach = max(float(np.linalg.norm(p)) for p in projectors) * 0.6 + 0.3
    colours = ("#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#F0E442", "#000000", "#999933")
    for ax, (i, j), names in ((axes[0], (0, 2), ("x (m, right)", "z (m, forward)")),
                              (axes[1], (2, 1), ("z (m, forward)", "y (m, down)"))):
        if points is not None and len(points):
            ax.scatter(points[:, i], points[:, j], s=2, c="#999999", label="surface", rasterized=True)
        ax.plot([0], [0], "s", color="#0072B2", label="camera")
        ax.annotate("", xy=(reach * (i == 2), reach * (j == 2)), xytext=(0, 0),
                    arrowprops={"arrowstyle": "->", "color": "#0072B2"})
        for k, (projector, direction) in enumerate(zip(projectors, directions)):
            colour = colours[k % len(colours)]
            ax.plot([projector[i]], [projector[j]], "o", color=colour,
                    label=f"projector {k + 1}" if len(projectors) > 1 else "projector")
            ax.annotate("", xy=(projector[i] + reach * direction[i], projector[j] + reach * direction[j]),
                        xytext=(projector[i], projector[j]), arrowprops={"arrowstyle": "->", "color": colour})
        ax.set_xlabel(names[0], fontsize=8)
        ax.set_ylabel(names[1], fontsize=8)
        ax.tick_params(labelsize=7)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    axes[1].invert_yaxis()  # y points down in the rig frame
    axes[0].set_title("from above", fontsize=9)
    axes[1].set_title("from the side", fontsize=9)
    axes[1].legend(fontsize=7, loc="center left", bbox_to_anchor=(1.02, 0.5), frameon=False)
    return _figure_uri(fig)


def regions(background: np.ndarray, outlines: Sequence[np.ndarray | None], boxes: Sequence[Sequence[int]],
            names: Sequence[str]) -> str:
    """The diagnosis's regions as outlines over the white capture, each in its own colour, with the legend beside
    the picture (not written over it); a region without a mask of its own is drawn as its box, dashed."""
    img = srgb_encode(np.nan_to_num(np.asarray(background, np.float32)))
    w, h = _panel_size(img.shape, 4.2)
    fig, axes = _figure(w + 4.2, max(h + 0.4, 0.45 * len(names) + 0.8))
    ax = axes[0]
    ax.imshow(img * 0.8, interpolation="nearest")
    handles = []
    drawn: list[np.ndarray] = []
    step = max(1, round(max(img.shape[:2]) / 120))  # pixels between nested outlines: visible at any size
    for k, (mask, box, name) in enumerate(zip(outlines, boxes, names)):
        colour = REGION_COLOURS[k % len(REGION_COLOURS)]
        if mask is not None and mask.any():
            # a region over the same place as an earlier one is drawn a little inside it, so both stay visible
            same = sum(1 for d in drawn if d.shape == mask.shape and np.array_equal(d, mask))
            drawn.append(mask)
            shape = mask.astype(np.uint8)
            if same:
                shape = cv2.erode(shape, np.ones((3, 3), np.uint8), iterations=2 * step * same)
            if not shape.any():
                shape = mask.astype(np.uint8)
            ax.contour(shape.astype(np.float32), levels=[0.5], colors=[colour], linewidths=2.0)
            handles.append(_mpl().lines.Line2D([], [], color=colour, lw=2.5, label=name))
        else:
            x, y, bw, bh = (float(v) for v in box)
            inset = 1.5 * k
            ax.add_patch(_mpl().patches.Rectangle((x - 0.5 + inset, y - 0.5 + inset), bw - 2 * inset, bh - 2 * inset,
                                       fill=False, ec=colour, lw=2.0, ls="--"))
            handles.append(_mpl().patches.Patch(fill=False, ec=colour, lw=2.0, ls="--", label=name))
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title("regions of the remaining error (white capture behind)", fontsize=9)
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.03, 1.0), fontsize=8, frameon=False,
              handlelength=2.2)
    return _figure_uri(fig)


def wrap(text: str, width: int = 48) -> str:
    """``text`` broken into lines of at most ``width`` characters, for a legend or a label."""
    return "\n".join(textwrap.wrap(text, width)) or text


def ranked_bars(names: Sequence[str], values: Sequence[float], *, xlabel: str, title: str,
                highlight: Sequence[str] = ()) -> str:
    """A horizontal bar chart, largest on top; ``highlight``: names drawn in the accent colour (e.g. selected)."""
    order = np.argsort(np.asarray(values, np.float64))
    fig, axes = _figure(6.4, 0.32 * len(names) + 1.0)
    ax = axes[0]
    colours = ["#D55E00" if names[i] in highlight else "#999999" for i in order]
    ax.barh([names[i] for i in order], [values[i] for i in order], color=colours)
    for y, i in enumerate(order):
        ax.text(values[i], y, f" {values[i]:.0%} " if values[i] >= 0 else f"{values[i]:.0%} ", va="center",
                ha="left" if values[i] >= 0 else "right", fontsize=7)
    ax.axvline(0, color="black", lw=0.6)
    ax.set_xlabel(xlabel, fontsize=8)
    ax.set_title(title, fontsize=9)
    ax.tick_params(labelsize=8)
    ax.xaxis.set_major_formatter(_mpl().ticker.PercentFormatter(1.0))
    ax.margins(x=0.15)
    return _figure_uri(fig)


def curve(labels: Sequence[str], values: Sequence[float], *, ylabel: str, title: str,
          reference: tuple[float, str] | None = None) -> str:
    """Values at named steps joined by a line (how the gap shrinks as effects are added); ``reference``: a
    dashed horizontal line and its label (the captures' noise)."""
    fig, axes = _figure(max(4.8, 0.75 * len(labels) + 1.5), 3.0)
    ax = axes[0]
    ax.plot(range(len(values)), values, "o-", color="#0072B2")
    for x, v in enumerate(values):
        ax.annotate(f"{v:.4f}", (x, v), textcoords="offset points", xytext=(0, 6), ha="center", fontsize=7)
    if reference is not None:
        ax.axhline(reference[0], color="#D55E00", ls="--", lw=1, label=reference[1])
        ax.legend(fontsize=7, frameon=False)
    ax.set_xticks(range(len(labels)), labels, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel(ylabel, fontsize=8)
    ax.set_ylim(bottom=0)
    ax.set_title(title, fontsize=9)
    ax.tick_params(axis="y", labelsize=7)
    ax.grid(alpha=0.3)
    return _figure_uri(fig)


def series(x: Sequence[float], lines: dict[str, Sequence[float]], *, xlabel: str, ylabel: str, title: str,
           levels: dict[str, float] | None = None, from_zero: bool = False) -> str:
    """Lines over frames (per-frame PSNR, solve time, flicker); ``levels``: dashed horizontal lines by label;
    ``from_zero``: the axis starts at 0 (a time, a change)."""
    fig, axes = _figure(6.4, 2.8)
    ax = axes[0]
    for k, (label, ys) in enumerate(lines.items()):
        ax.plot(x, ys, "o-" if len(x) < 40 else "-", ms=3, label=label, color=REGION_COLOURS[(k + 4) % 7])
    for k, (label, v) in enumerate((levels or {}).items()):
        ax.axhline(v, ls="--", lw=1, color=("#999999", "#D55E00", "#009E73")[k % 3], label=label)
    ax.set_xlabel(xlabel, fontsize=8)
    ax.set_ylabel(ylabel, fontsize=8)
    ax.set_title(title, fontsize=9)
    ax.tick_params(labelsize=7)
    ax.xaxis.set_major_locator(_mpl().ticker.MaxNLocator(integer=True))  # frames are whole numbers
    if from_zero:
        ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    if len(lines) + len(levels or {}) > 1:
        ax.legend(fontsize=7, frameon=False, loc="center left", bbox_to_anchor=(1.02, 0.5))
    return _figure_uri(fig)


def grouped_bars(groups: Sequence[str], bars: dict[str, Sequence[float | None]], *, ylabel: str, title: str) -> str:
    """Bars side by side per group (per target: uncompensated, compensated and the ceilings), missing ones left
    out."""
    fig, axes = _figure(max(4.8, 1.6 * len(groups) + 2.4), 2.8)
    ax = axes[0]
    n = len(bars)
    width = 0.8 / max(n, 1)
    palette = ("#999999", "#0072B2", "#009E73", "#E69F00", "#CC79A7")
    for k, (label, values) in enumerate(bars.items()):
        xs = [g + (k - (n - 1) / 2) * width for g, v in enumerate(values) if v is not None]
        ys = [float(v) for v in values if v is not None]
        ax.bar(xs, ys, width, label=label, color=palette[k % len(palette)])
        for x, y in zip(xs, ys):
            ax.text(x, y, f"{y:.1f}", ha="center", va="bottom", fontsize=6)
    ax.set_xticks(range(len(groups)), groups, fontsize=8)
    ax.set_ylabel(ylabel, fontsize=8)
    ax.set_title(title, fontsize=9)
    ax.tick_params(axis="y", labelsize=7)
    ax.legend(fontsize=7, frameon=False, loc="center left", bbox_to_anchor=(1.02, 0.5))
    ax.grid(axis="y", alpha=0.3)
    return _figure_uri(fig)
