"""The projector window: a borderless window that shows a frame pixel for pixel on the projector's display.

Why SDL2 through pygame-ce: its wheels carry SDL2 itself on Linux, Windows and
macOS, so the window needs nothing outside ProCam's own dependencies (OpenCV's
pip build has no GUI at all), SDL knows every display's index and size, and a
software surface is blitted 1:1 — no scaling, no colour management, no
filtering. pygame-ce is the maintained branch of pygame (same import name).

Where the window goes: ``display=N`` covers display N exactly (a borderless
window of the display's size, centred on it — what "desktop full screen" is,
without a mode change), and refuses when the display's size is not the
projector's native frame (the OS would scale); ``position=(x, y)`` puts a
frame-sized borderless window at desktop coordinates, for set-ups where the
projector is part of a larger desktop.

Present, then wait: :meth:`ProjectorWindow.show` blits, flips and returns the
time the flip returned. SDL cannot tell when the projector has actually
scanned the frame out (vsync, compositor and the projector's own input lag
differ per machine), so the live device measures the whole chain from this
time to the camera seeing the change, once, and waits it out on every capture
(``device.py``).

Several projectors: one :class:`ProjectorWindow` per projector display, all
in this process. pygame-ce's ``Window`` is SDL2's multi-window API (each window
its own surface and flip, one event queue for all), so no helper process, pipe
or second SDL is needed, and the flips of all windows are timed on one clock
by the thread that captures. The device draws every window first
(:meth:`ProjectorWindow.put`) and then flips them one after the other
(:meth:`ProjectorWindow.flip`), so the last flip's time bounds them all.
"""

from __future__ import annotations

import os
import time
from typing import Any

import numpy as np

from ..errors import LiveError

#: SDL_WINDOWPOS_CENTERED_DISPLAY(n) is this mask | n (SDL_video.h).
_CENTRED_ON_DISPLAY = 0x2FFF0000


class WindowClosed(LiveError):
    """The projector window was closed by its user (Esc, or the window manager's close)."""


def _pygame() -> Any:
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    try:
        import pygame
    except ImportError as exc:  # pragma: no cover - pygame-ce is a pinned requirement
        raise LiveError(f"the projector window needs pygame-ce (pip install pygame-ce): {exc}") from None
    return pygame


#: SDL's video drivers that draw where nobody sees: SDL falls back to them when there is no desktop to draw on.
_UNSEEN_DRIVERS = ("offscreen", "dummy", "evdev")


def _no_display(why: str) -> LiveError:
    return LiveError(f"no display to open the projector window on ({why}). Run on the machine the projector is "
                     "plugged into, inside its desktop session (not over SSH), or use the folder workflow "
                     "(`procam patterns` / `procam import-captures`)")


def _init_video(pygame: Any) -> None:
    if pygame.display.get_init():
        return
    try:
        pygame.display.init()
    except pygame.error as exc:
        raise _no_display(str(exc)) from None
    driver = str(pygame.display.get_driver())
    asked = os.environ.get("SDL_VIDEODRIVER", "").strip().lower()
    # a driver nobody sees is taken only when asked for by name (a test's virtual display, a headless check)
    if driver.lower() in _UNSEEN_DRIVERS and driver.lower() != asked:
        pygame.display.quit()
        raise _no_display(f"no desktop session was found, and SDL's '{driver}' driver draws where nobody sees")


def list_displays() -> list[tuple[int, int, int, float]]:
    """``(index, width, height, refresh Hz)`` of every display SDL sees (refresh 0 when unknown)."""
    pygame = _pygame()
    _init_video(pygame)
    sizes = pygame.display.get_desktop_sizes()
    rates = pygame.display.get_desktop_refresh_rates()
    return [(i, int(w), int(h), float(rates[i]) if i < len(rates) else 0.0) for i, (w, h) in enumerate(sizes)]


def _check_on_desktop(where: tuple[int, int], size: tuple[int, int], displays: list[tuple[int, int, int, float]],
                      who: str) -> None:
    """Refuse a window at desktop position ``where`` that lies entirely off the desktop: nobody would see it. With
    one display the desktop is that display; with several SDL does not say where each lies, so only a window off
    every place they could lie (each one's size, summed, on every side of the first) is refused."""
    if not displays:
        return
    x, y = where
    w, h = size
    if len(displays) == 1:
        left, top, right, bottom = 0, 0, displays[0][1], displays[0][2]
        desktop = f"its one display is {right}×{bottom}, from 0:0"
    else:
        wide, tall = sum(d[1] for d in displays), sum(d[2] for d in displays)
        left, top, right, bottom = -wide, -tall, wide, tall
        desktop = f"{len(displays)} displays of {', '.join(f'{d[1]}×{d[2]}' for d in displays)}"
    if x + w <= left or x >= right or y + h <= top or y >= bottom:
        raise LiveError(f"{who}'s window of {w}×{h} at {x}:{y} lies entirely off the desktop ({desktop}): give the "
                        "desktop position of the projector's output (its top-left corner), or display=N")


class ProjectorWindow:
    """A borderless window of the projector's native size on its display; frames are float H×W×3 in [0, 1]."""

    def __init__(self, size: tuple[int, int], *, display: int | None = None,
                 position: tuple[int, int] | None = None, title: str = "ProCam projector",
                 who: str = "the projector") -> None:
        if (display is None) == (position is None):
            raise LiveError("place the projector window either on a display (display=N) or at a desktop "
                            "position (position=X:Y), not both or neither")
        pygame = self._pg = _pygame()
        _init_video(pygame)
        self.size = (int(size[0]), int(size[1]))
        self.refresh_hz = 60.0
        if display is not None:
            displays = list_displays()
            if not 0 <= display < len(displays):
                raise LiveError(f"there is no display {display}: SDL sees {len(displays)} "
                                f"({', '.join(f'{i}: {w}×{h}' for i, w, h, _ in displays)})")
            _, w, h, hz = displays[display]
            if (w, h) != self.size:
                raise LiveError(f"display {display} is {w}×{h} but {who}'s native frame is "
                                f"{self.size[0]}×{self.size[1]}: set that display to the projector's native "
                                "resolution (the OS would otherwise scale every pattern), or choose another display")
            where = (_CENTRED_ON_DISPLAY | display, _CENTRED_ON_DISPLAY | display)
            self.refresh_hz = hz or self.refresh_hz
        else:
            where = (int(position[0]), int(position[1]))
            _check_on_desktop(where, self.size, list_displays(), who)
        try:
            self._window = pygame.Window(title, self.size, position=where, borderless=True)
        except (pygame.error, ValueError) as exc:
            raise LiveError(f"cannot open the projector window: {exc}") from None
        self._window.always_on_top = True
        self._surface = self._window.get_surface()
        self._buffer = np.zeros((self.size[0], self.size[1], 3), dtype=np.uint8)  # SDL surfaces are x-major

    @property
    def position(self) -> tuple[int, int]:
        """The window's top-left in desktop coordinates."""
        x, y = self._window.position
        return int(x), int(y)

    def _pump(self) -> None:
        pygame = self._pg
        for event in pygame.event.get():
            if event.type == pygame.QUIT or (event.type == pygame.KEYDOWN and event.key == pygame.K_ESCAPE):
                raise WindowClosed("the projector window was closed (Esc): the live session stops here; run the "
                                "same command again to resume where it stopped")

    def poll(self) -> None:
        """Handle the window's events between flips (a loop that shows nothing new for a while): Esc or a close
        raises :class:`WindowClosed`."""
        self._pump()

    def put(self, frame: np.ndarray) -> None:
        """Draw ``frame`` (H×W×3 floats in [0, 1], or 8-bit levels RGB or RGBX, the native size) into the window's
        buffer without showing it yet: several windows are drawn first and flipped one right after the other
        (``device.py``). Values become 8-bit levels with no transfer curve."""
        f = np.asarray(frame)
        w, h = self.size
        if f.shape[:2] != (h, w):
            raise LiveError(f"a projector frame must be {w}×{h}, got {f.shape[1]}×{f.shape[0]}")
        if f.dtype == np.uint8 and f.ndim == 3 and f.shape[2] in (3, 4):
            # Levels row by row, as SDL stores an RGB(X) surface: blitted from the array's memory, no transpose.
            layout = "RGB" if f.shape[2] == 3 else "RGBX"
            self._surface.blit(self._pg.image.frombuffer(np.ascontiguousarray(f), self.size, layout), (0, 0))
            return
        levels = np.clip(np.rint(f * 255.0), 0, 255).astype(np.uint8)
        if levels.ndim == 2:
            levels = levels[..., None]
        self._buffer[...] = levels.transpose(1, 0, 2)
        self._pg.surfarray.blit_array(self._surface, self._buffer)

    def flip(self) -> float:
        """Show what :meth:`put` drew and return when the flip returned (``time.perf_counter``)."""
        self._window.flip()
        self._pump()
        return time.perf_counter()

    def show(self, frame: np.ndarray) -> float:
        """Show ``frame`` (:meth:`put`, then :meth:`flip`) and return when the flip returned."""
        self.put(frame)
        return self.flip()

    def frame_period(self) -> float:
        """One refresh of the display, seconds (60 Hz where SDL does not know)."""
        return 1.0 / self.refresh_hz

    def close(self) -> None:
        window, self._window = getattr(self, "_window", None), None
        if window is not None:
            window.destroy()
            self._pg.event.pump()


__all__ = ["ProjectorWindow", "WindowClosed", "list_displays"]
