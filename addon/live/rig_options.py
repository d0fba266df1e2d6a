"""The live rig as the sidebar's Live panel sets it, each field declared once.

The panel's scene properties are made from these declarations (label, help, default, limits, choices), and
:meth:`LiveRigOptions.device` turns the values into the ``live:…`` device string the command line takes (parsed
by :class:`~.device.LiveSpec`, so a value the parser refuses is refused here with the field's name).
"""

from __future__ import annotations

from dataclasses import dataclass

from ..errors import LiveError
from ..options import Choice, option
from .device import LiveSpec


@dataclass
class LiveRigOptions:
    """The projector window(s) and the camera of a live rig (module doc); not options of a command (``flag=""``):
    the command line gives the whole rig as one ``--device live:…``."""

    camera: str = option(
        "0", flag="", label="Camera", prop="procam_live_camera",
        help="the camera: an index (0, 1 …), a device path (/dev/video2) or a URL (http://…/video.mjpg from a "
             "network camera or a phone, rtsp://…)")
    placement: str = option(
        "DISPLAY", flag="", label="Window", prop="procam_live_placement", help="where the projector window opens",
        choices=(Choice("DISPLAY", "Display", "Cover one display exactly (its size must be the projector's native "
                                              "size): the projector as its own screen"),
                 Choice("POSITION", "Position", "A projector-sized window at desktop coordinates: the projector as "
                                                "part of a larger desktop")))
    display: str = option(
        "1", flag="", label="Display", prop="procam_live_display",
        help="index of the projector's display (Check Live Rig lists them; 0 is usually the main one); a rig of "
             "several projectors: one per projector in rig order, joined by + (1+2)")
    position: str = option(
        "0:0", flag="", label="Position", prop="procam_live_position",
        help="top-left corner X:Y of the projector window in desktop pixels; a rig of several projectors: one per "
             "projector in rig order, joined by + (40:30+300:30)")
    average: int = option(
        1, min=1, max=64, flag="", label="Frames Averaged", prop="procam_live_average",
        help="camera frames averaged per capture: more lowers the camera's noise, each costs one frame")
    encoding: str = option(
        "srgb", flag="", label="Camera Encoding", prop="procam_live_encoding", help="what the camera delivers",
        choices=(Choice("srgb", "sRGB", "The camera delivers sRGB-encoded 8-bit frames (webcams, network cameras, "
                                        "phones)"),
                 Choice("linear", "Linear", "The camera delivers linear values")))
    latency_auto: bool = option(
        True, flag="", label="Measure Latency", prop="procam_live_latency_auto",
        help="measure the time from showing a frame to the camera seeing it when the rig opens (off: use the "
             "latency given)")
    latency: float = option(
        0.2, min=0.0, max=9.99, flag="", label="Latency", prop="procam_live_latency",
        help="seconds from showing a frame to the camera delivering it")
    check_exposure: bool = option(
        True, flag="", label="Check Exposure Lock", prop="procam_live_check_exposure",
        help="refuse a camera whose exposure or white balance still adapts (and check the captured set the same "
             "way); off only for a camera known to be locked")

    def window(self) -> str:
        """The projector window(s) as the device string says them: ``display=N`` or ``position=X:Y``; a rig of
        several projectors one each, in rig order, joined by ``+`` (``display=1+2``, ``position=X:Y+X:Y``)."""
        if self.placement == "DISPLAY":
            key, field, form = "display", "Display", "a display index (1), or one per projector joined by + (1+2)"
            typed = self.display
        else:
            key, field, form = "position", "Position", "X:Y in desktop pixels (40:30), or one per projector " \
                                                       "joined by + (40:30+300:30)"
            typed = self.position
        value = "".join(typed.split())  # spaces typed around + or : are no part of the value
        # numbers, + and : alone: a comma would slip another key (a camera) into the device string
        if not value or value.strip("0123456789+:-"):
            raise LiveError(f"the Live panel's {field} must be {form}, got {typed!r}")
        try:
            LiveSpec.parse(f"{key}={value}", camera_required=False)
        except LiveError as exc:
            raise LiveError(f"the Live panel's {field} must be {form}, got {typed!r} ({exc})") from None
        return f"{key}={value}"

    def device(self) -> str:
        """The ``live:…`` device string (checked: a clear LiveError when a field is wrong)."""
        camera = self.camera.strip()
        if not camera:
            raise LiveError("no live camera: type its index (0), device path (/dev/video2) or URL in the Live panel")
        parts = [f"camera={camera}", self.window(), f"average={self.average}", f"encoding={self.encoding}",
                 "latency=auto" if self.latency_auto else f"latency={self.latency:.4g}"]
        spec = "live:" + ",".join(parts)
        LiveSpec.parse(spec)  # a camera that is no index, path or URL fails here, with the parser's message
        return spec


__all__ = ["LiveRigOptions"]
