"""What the lab's camera records of a perfect answer: the ceiling no compensation can pass, known to the lab alone.

``procam evaluate`` holds a result to the *noise ceiling*: the camera's noise
measured from two captures of the answer. That is all a real rig can know, and
on a camera that writes raw values it is the ceiling. A camera that writes
JPEG (the lab of other forms, a phone) also quantises every photograph's
texture, an error that depends on the image and is the same in two shots of
it: the difference of two captures does not see it, and what it does see (the
sensor noise the compression keeps) depends on the answer's own texture. A
blurred answer reads a quieter camera than a sharp one.

The lab knows its camera, so it can say what a perfect answer scores: the
capture whose noiseless value is the target at every pixel. Its signal at the
sensor is the target through the inverse of the camera's processing (white
balance, tone curves: per channel and monotone, inverted by bisection); the
capture is that signal through the camera as the lab renders it (sensor
noise, processing, 16-bit or JPEG recording). Benchmarks compare with it; no
stage may (``tests/test_architecture.py``: only the lab and benchmarks know
the lab's forms).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from .effects import record_signal
from .other_forms import OtherForms
from .truth import LabTruth

#: Bisection steps for the inverse of the camera's processing: 2⁻³⁰ of the sensor's range, far below a 16-bit level.
BISECTION_STEPS = 30


def sensor_signal(truth: LabTruth, target: np.ndarray) -> np.ndarray:
    """The linear signal at the lab camera's sensor whose noiseless recording is ``target`` (H×W×3, the captures'
    units), clipped to what the sensor holds ([0, 1])."""
    other = OtherForms(truth.other_forms, truth.first_projector)
    effects = truth.effects

    def noiseless(signal: np.ndarray) -> np.ndarray:
        recorded = record_signal(signal, effects, None)
        return other.camera_tone(recorded) if other.active else recorded

    t = np.asarray(target, np.float32)
    lo, hi = np.zeros_like(t), np.ones_like(t)
    for _ in range(BISECTION_STEPS):
        mid = 0.5 * (lo + hi)
        below = noiseless(mid) < t
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    return 0.5 * (lo + hi)


def render_noise(truth: LabTruth, frames: Sequence[np.ndarray], seed: int = 0) -> np.ndarray:
    """One draw of the lab's render noise at the sensor (camera-sized H×W×3): the difference of two renders of
    ``frames`` (one per projector, an answer whose light is near the target's) with the sensor's noise and the
    other-forms camera off, over √2. A path tracer's noise is what a capture of even a perfect answer carries
    besides the sensor's."""
    from .cycles_device import LabDevice

    quiet = replace(truth.without("noise"), other_forms=0.0)
    with LabDevice(quiet, seed=seed) as device:
        first, second = device.project_all(list(frames)), device.project_all(list(frames))
    return ((first - second) / math.sqrt(2.0)).astype(np.float32)


def perfect_capture(truth: LabTruth, target: np.ndarray, rng: np.random.Generator,
                    render: np.ndarray | None = None) -> np.ndarray:
    """One capture by the lab's camera of a perfect answer to ``target`` (camera-sized H×W×3, the captures' units):
    :func:`sensor_signal`, plus the render's noise ``render`` (:func:`render_noise`) when given, through the
    camera's noise, processing and recording, with ``rng`` drawing the sensor's noise. (The render's noise is
    added at the sensor, where it is measured on a lab without a camera curve.)"""
    return _recorded(truth, sensor_signal(truth, target), rng, render)


def _recorded(truth: LabTruth, signal: np.ndarray, rng: np.random.Generator,
              render: np.ndarray | None) -> np.ndarray:
    """The lab camera's capture of the sensor ``signal`` (plus ``render``): :func:`perfect_capture`'s last part."""
    if render is not None:
        signal = np.clip(signal + render, 0.0, None)
    other = OtherForms(truth.other_forms, truth.first_projector)
    return other.camera_record(record_signal(signal, truth.effects, rng))


def perfect_ceiling(truth: LabTruth, shown: np.ndarray, inside: tuple[slice, slice], *,
                    target: np.ndarray | None = None, render: np.ndarray | None = None, draws: int = 2,
                    seed: int = 0) -> float:
    """The PSNR (dB) over ``inside`` against ``target`` (``shown[inside]`` when None) of the lab camera's captures
    of an answer that makes its noiseless recording ``shown`` (camera-sized): the mean squared error of ``draws``
    captures, each drawing its own sensor noise (``render``: the render's, :func:`render_noise`). ``shown`` the
    target itself: a perfect answer's ceiling; the target
    within the colours each pixel can show: the best any answer can score."""
    rng = np.random.default_rng(seed)
    s = np.asarray(shown, np.float32)
    ref = s[inside] if target is None else np.asarray(target, np.float32)
    signal = sensor_signal(truth, s)  # the same for every draw: only the noise differs
    mse = float(np.mean([np.mean((_recorded(truth, signal, rng, render)[inside] - ref) ** 2) for _ in range(draws)]))
    return float(10.0 * np.log10(1.0 / max(mse, 1e-12)))


__all__ = ["perfect_capture", "perfect_ceiling", "render_noise", "sensor_signal"]
