"""A loopback camera: films the projector window off the screen and streams it as MJPEG over HTTP on 127.0.0.1.

It lets the live loop run end to end with real parts and no hardware: the
projector window is a real window (on a virtual X server in the tests), and
the camera is a real network client (OpenCV ``VideoCapture`` over HTTP), as a
network camera or a phone used as a webcam would be. Between the two, each
grabbed screen area goes through what a surface and a camera would do to it:

* a planar surface seen from another viewpoint: a homography from camera
  pixels to projector pixels (:meth:`LoopbackRig.for_plane` computes it, and the
  matching depth map, from a camera, a projector and a plane);
* the projector's defocus (a Gaussian blur), the surface's paint (a gain map),
  stray light (an offset), the camera's noise;
* the camera's latency (frames are served ``delay_s`` after they were grabbed)
  and, on request, auto exposure (a gain that drifts towards a mid-grey
  picture, as a camera left on auto does).

Frames are 8-bit JPEG of linear values (use ``encoding=linear`` in the device).
:func:`painted_wall` is the rig the tests and ``scripts/bench_live.py`` use.
"""

from __future__ import annotations

import http.server
import threading
import time
from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import LiveError
from ..rig.demo import demo_rig
from ..rig.model import Camera, Projector

#: Auto exposure drives the picture's mean towards this level with this time constant (seconds).
AUTO_TARGET, AUTO_TAU = 0.45, 0.3


@dataclass
class LoopbackRig:
    """What the loopback camera does to the screen area it films."""

    region: tuple[int, int, int, int]  # left, top, width, height on the screen: the projector window
    camera_size: tuple[int, int]
    #: camera pixel → projector pixel (OpenCV pixel centres); None: the region resized to the camera
    homography: np.ndarray | None = None
    blur_px: float = 0.0
    gain: float | np.ndarray = 1.0  # scalar or camera-sized H×W×3
    offset: float = 0.0
    noise: float = 0.0
    delay_s: float = 0.0
    fps: float = 30.0
    auto_exposure: bool = False
    quality: int = 95

    @staticmethod
    def for_plane(camera: Camera, projector: Projector, point: np.ndarray, normal: np.ndarray,
                  region_origin: tuple[int, int]) -> tuple[LoopbackRig, np.ndarray]:
        """The homography a plane (``point``, ``normal`` in the rig frame) induces between the camera and the
        projector, and the camera's depth map of it (metres, z; 0 where the ray misses or faces away)."""
        cw, ch = camera.intrinsics.size
        u, v = np.meshgrid(np.arange(cw) + 0.5, np.arange(ch) + 0.5)
        rays = camera.intrinsics.rays(np.stack([u.ravel(), v.ravel()], axis=1))
        n, p0 = np.asarray(normal, float), np.asarray(point, float)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (p0 @ n) / (rays @ n)
        s = np.where(np.isfinite(s) & (s > 0), s, np.nan)
        points = rays * s[:, None]
        depth = np.nan_to_num(points[:, 2].reshape(ch, cw), nan=0.0).astype(np.float32)
        proj = projector.project(points)
        ok = np.isfinite(proj).all(axis=1)
        if ok.sum() < 8:
            raise LiveError("the loopback plane is not seen by both the camera and the projector")
        cam_cv = np.stack([u.ravel(), v.ravel()], axis=1)[ok] - 0.5
        h, _ = cv2.findHomography(cam_cv, proj[ok] - 0.5, 0)
        pw, ph = projector.intrinsics.size
        return LoopbackRig((region_origin[0], region_origin[1], pw, ph), (cw, ch), homography=h), depth


def painted_wall(size: tuple[int, int], origin: tuple[int, int], *, delay_s: float = 0.0,
                 auto_exposure: bool = False) -> tuple[LoopbackRig, np.ndarray, Projector]:
    """The demo rig (``rig/demo.py``, at ``size`` for camera and projector) before a painted wall tilted 10°:
    the loopback rig, the camera's depth map of the wall, and the true projector (its pose is what calibration
    should find). The paint is stripes of another colour; a little defocus, stray light and noise."""
    rig = demo_rig(size, size)
    loop, depth = LoopbackRig.for_plane(rig.camera, rig.projector, np.array([0.0, 0.0, 1.7]),
                                        np.array([0.0, 0.17, -1.0]), origin)
    w, h = size
    x = np.arange(w, dtype=np.float32)[None, :, None] / max(w, h)
    stripes = (np.sin(x * 14.0) > 0.6).astype(np.float32)
    loop.gain = np.broadcast_to(0.8 - 0.25 * stripes * np.array([0.2, 1.0, 0.6], np.float32), (h, w, 3)).copy()
    loop.offset, loop.blur_px, loop.noise = 0.03, 0.8, 0.01
    loop.delay_s, loop.auto_exposure = delay_s, auto_exposure
    return loop, depth, rig.projector


class LoopbackCamera:
    """Grabs ``rig.region`` at ``rig.fps`` and serves it at ``url`` (multipart MJPEG). Use as a context manager."""

    def __init__(self, rig: LoopbackRig, *, port: int = 0) -> None:
        try:
            import mss  # a dev requirement: only the loopback rig films the screen
            import mss.exception
        except ImportError:
            raise LiveError("the loopback camera needs the mss package (pip install mss)") from None
        self._mss = mss
        self.rig = rig
        self._frames: deque[tuple[float, bytes]] = deque(maxlen=max(8, int(rig.fps * (rig.delay_s + 2))))
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._exposure = 1.0
        self.failure: str | None = None
        self._rng = np.random.default_rng(0)
        self._grabber = threading.Thread(target=self._grab_loop, name="procam-loopback-grab", daemon=True)
        owner = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # noqa: N802 (http.server's name)
                owner._serve(self)

            def log_message(self, *args: object) -> None:
                pass

        self._server = http.server.ThreadingHTTPServer(("127.0.0.1", port), Handler)
        self._server.daemon_threads = True
        self.url = f"http://127.0.0.1:{self._server.server_address[1]}/stream.mjpg"
        self._server_thread = threading.Thread(target=self._server.serve_forever, name="procam-loopback-http",
                                               daemon=True)
        self._grabber.start()
        self._server_thread.start()

    # -- the "camera" ------------------------------------------------------------------------------------------

    def _picture(self, grab: np.ndarray) -> np.ndarray:
        rig = self.rig
        img = grab[..., 2::-1].astype(np.float32) / 255.0  # BGRA → RGB, the projector's levels
        if rig.blur_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), rig.blur_px)
        w, h = rig.camera_size
        if rig.homography is not None:
            img = cv2.warpPerspective(img, rig.homography, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                      borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        elif img.shape[:2] != (h, w):
            img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
        img = img * rig.gain + rig.offset
        if rig.auto_exposure:
            mean = float(img.mean()) * self._exposure
            step = (AUTO_TARGET / max(mean, 1e-3)) ** min(1.0, 1.0 / (rig.fps * AUTO_TAU))
            self._exposure = float(np.clip(self._exposure * step, 0.25, 4.0))
            img = img * self._exposure
        if rig.noise > 0:
            img = img + self._rng.normal(0.0, rig.noise, img.shape).astype(np.float32)
        return np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)

    def _grab_loop(self) -> None:
        left, top, width, height = self.rig.region
        area = {"left": int(left), "top": int(top), "width": int(width), "height": int(height)}
        period = 1.0 / self.rig.fps
        with self._mss.MSS() as screen:
            next_t = time.perf_counter()
            while not self._stop.is_set():
                stamp = time.perf_counter()
                try:
                    picture = self._picture(np.asarray(screen.grab(area)))
                except self._mss.exception.ScreenShotError as exc:  # e.g. the area leaves the screen
                    self.failure = f"cannot film {area}: {exc}"
                    self._stop.set()
                    return
                ok, jpeg = cv2.imencode(".jpg", picture[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, self.rig.quality])
                if ok:
                    with self._cond:
                        self._frames.append((stamp, jpeg.tobytes()))
                        self._cond.notify_all()
                next_t += period
                time.sleep(max(0.0, next_t - time.perf_counter()))

    def _serve(self, handler: http.server.BaseHTTPRequestHandler) -> None:
        handler.send_response(200)
        handler.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
        handler.send_header("Cache-Control", "no-cache")
        handler.end_headers()
        sent = time.perf_counter() - self.rig.delay_s - 1.5 / self.rig.fps  # start from the newest due frame
        try:
            while not self._stop.is_set():
                with self._cond:
                    # The newest frame grabbed at least delay_s ago: what a camera with that latency delivers now.
                    due = time.perf_counter() - self.rig.delay_s
                    ready = [(s, b) for s, b in self._frames if sent < s <= due]
                    if not ready:
                        self._cond.wait(0.005)
                        continue
                stamp, jpeg = ready[0]
                sent = stamp
                handler.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n"
                                    % len(jpeg) + jpeg + b"\r\n")
                handler.wfile.flush()
        except (BrokenPipeError, ConnectionResetError):
            pass

    def close(self) -> None:
        self._stop.set()
        self._server.shutdown()
        self._server.server_close()
        self._grabber.join(timeout=2.0)

    def __enter__(self) -> LoopbackCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["LoopbackCamera", "LoopbackRig"]
