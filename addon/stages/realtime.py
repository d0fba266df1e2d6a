"""Stage C in real time: a precomputed approximate inverse of the light-transport operator, and one solver step.

A live source gives a new target every 33 ms; the ``transport`` schedule's
forty SIRT steps take a second. What makes real time reachable is that the
direct part ``D`` of ``T`` (stages/transport.py) is sparse and almost local:
a camera pixel sees the few texels under its footprint. Its right inverse of
least C-norm, ``C⁻¹ Dᵀ (D C⁻¹ Dᵀ)⁻¹`` (``C``: each texel's total light, so a
flat target gives a flat input), is then almost local too, because
``G = D C⁻¹ Dᵀ`` couples a pixel only with the pixels within a few of its own.
The *approximate inverse* keeps that locality: ``A = C⁻¹ Dᵀ M`` with ``M`` a
3 × 3 stencil per camera pixel and channel, the sparse approximate inverse of
``G`` on that pattern (SPAI: column ``j`` of ``M`` minimises ``‖G mⱼ − eⱼ‖²``,
a 9-unknown least-squares problem per pixel, with a small ridge). Applying
``A`` is one 9-tap gather and one back-projection through ``D``, both Dr.Jit
gathers: about the cost of a SIRT step (4 ms against 5 at 800×600 on 2 cores).
Measured on the lab's curve at 800×600: the inverse alone is 1.4–3.4 dB below
the 40-step solve on the operator, one SIRT step from it brings it within
0.15 dB (0.25 dB captured, ``scripts/bench_live_show.py``); without ``C`` (the
plain least-norm inverse) the one-pass answer was 0.15–0.3 dB lower still.

Per frame (:class:`RealtimeView`): the target and θ in camera space become
the light wanted from the projector, ``(y_t + θ) / g`` minus the indirect
light of the previous frame's answer (interreflection is smooth and changes
slowly, so the last frame's is a good estimate); ``A`` maps it to the input;
the box ``[0, 1]`` clips it; then ``steps`` SIRT steps on ``T`` with that
interreflection held. Consecutive video frames are close, so where the
picture holds still the frames' steps add up, as a warm-started solve's do.

The inverse is stored beside the operator (``inverse.npz``, ``inverse.json``
with the calibration's hashes: ``steps/inverse.py``) and refused for another
calibration, like the operator.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ..errors import ProCamError
from ..progress import Progress, quiet
from .transport import BlurredRows, TransportOperator, TransportRows, gaussian_taps, lens_blur
from .warp_model import bilinear_taps, pixel_centres

FORMAT, VERSION = "procam-inverse", 1
#: stencil radius of M (1: 3 × 3 pixels) and the farthest pixel offset of G kept (pixels sharing a texel)
STENCIL, COUPLING = 1, 4
#: ridge of the local least squares, relative to each system's mean diagonal
RIDGE = 1e-3
#: ridge of the lens blur's one-dimensional regularised inverse (:func:`deblur_taps`): 0.1–0.3 did best on the lab's
#: curve at 800×600 (σ 0.74 texels, one refinement step; 0.02 and 1.0 were 0.04–0.18 dB lower on the operator)
DEBLUR_RIDGE = 0.2
#: solves of the first frame before its answer, each taking its interreflection from the one before
#: (:meth:`RealtimeView.solve`): three settle its level to within 0.0003 of the next frames'
FIRST_FRAME_SOLVES = 3


class InverseError(ProCamError):
    """The approximate inverse cannot be built, read or used with this calibration."""


def building_bytes(camera_size: tuple[int, int]) -> int:
    """The most memory building the inverse takes: the bands of ``G`` and ``G²`` for one channel at a time."""
    cw, ch = camera_size
    g_bands = (2 * COUPLING + 1) ** 2
    g2_bands = (4 * STENCIL + 1) ** 2
    return int(cw * ch * 8 * (g_bands + g2_bands + 4 * (2 * STENCIL + 1) ** 4))


@dataclass
class ApproximateInverse:
    """``M`` of ``A = C⁻¹ Dᵀ M`` (module doc) for one operator: per camera pixel and channel, the weights of its
    3 × 3 neighbours' wanted light (``weight[p, a, c]``: neighbour ``p − offset[a]``)."""

    camera_size: tuple[int, int]
    input_size: tuple[int, int]
    weight: np.ndarray  # (P, 9, 3) float32
    report: dict[str, Any] = field(default_factory=dict)

    @staticmethod
    def offsets() -> np.ndarray:
        """(9, 2) the stencil's (dy, dx), row-major."""
        r = np.arange(-STENCIL, STENCIL + 1)
        dy, dx = np.meshgrid(r, r, indexing="ij")
        return np.stack([dy.ravel(), dx.ravel()], axis=1)

    def arrays(self) -> dict[str, np.ndarray]:
        return {"weight": self.weight, "camera_size": np.asarray(self.camera_size),
                "input_size": np.asarray(self.input_size)}

    @property
    def nbytes(self) -> int:
        return int(self.weight.nbytes)

    @staticmethod
    def from_arrays(data: Any, report: dict[str, Any] | None = None) -> ApproximateInverse:
        try:
            inv = ApproximateInverse(tuple(int(v) for v in data["camera_size"]),
                                     tuple(int(v) for v in data["input_size"]),
                                     np.asarray(data["weight"], np.float32), dict(report or {}))
        except (KeyError, ValueError, TypeError) as exc:
            raise InverseError(f"the stored approximate inverse is incomplete ({exc}); run procam precompute "
                               "--live again") from None
        cw, ch = inv.camera_size
        if inv.weight.shape != (cw * ch, (2 * STENCIL + 1) ** 2, 3):
            raise InverseError("the stored approximate inverse has the wrong shape; run procam precompute --live "
                               "--force")
        if not np.all(np.isfinite(inv.weight)):  # one NaN weight would spread into every live frame it touches
            raise InverseError("the stored approximate inverse holds weights that are no number; run procam "
                               "precompute --live --force")
        return inv

    def fits(self, op: TransportOperator) -> bool:
        return tuple(self.camera_size) == tuple(op.camera_size) and tuple(self.input_size) == tuple(op.input_size)


def _shift(image: np.ndarray, dy: int, dx: int) -> np.ndarray:
    """``out[y, x] = image[y + dy, x + dx]`` (zero beyond the edges) for an (H, W, …) array."""
    out = np.zeros_like(image)
    h, w = image.shape[:2]
    ys, yd = (slice(dy, h), slice(0, h - dy)) if dy >= 0 else (slice(0, h + dy), slice(-dy, h))
    xs, xd = (slice(dx, w), slice(0, w - dx)) if dx >= 0 else (slice(0, w + dx), slice(-dx, w))
    out[yd, xd] = image[ys, xs]
    return out


def _coupling_bands(op: TransportOperator, channel: int) -> np.ndarray:
    """``G = D Dᵀ`` of one channel as bands: ``(band, H, W)`` with ``G(p, p + o)`` for the offsets ``o`` within
    :data:`COUPLING` (row-major over dy, dx). Pairs of pixels farther apart that share a texel are dropped (their
    light is counted in neither)."""
    cw, ch = op.camera_size
    p_all = cw * ch
    k = op.index.shape[1]
    w = op.weight[:, :, channel].ravel()
    live = np.flatnonzero(w > 0)
    pixel = (live // k).astype(np.int64)
    texel = op.index.ravel()[live].astype(np.int64)
    order = np.argsort(texel, kind="stable")
    pixel, texel, w = pixel[order], texel[order], w[live][order]
    starts = np.flatnonzero(np.r_[True, texel[1:] != texel[:-1]])
    counts = np.diff(np.r_[starts, len(texel)])
    slot = np.arange(len(texel)) - np.repeat(starts, counts)
    n, kc = len(starts), int(counts.max(initial=1))
    pad_p = np.full((n, kc), -1, np.int64)
    pad_w = np.zeros((n, kc), np.float64)
    group = np.repeat(np.arange(n), counts)
    pad_p[group, slot] = pixel
    pad_w[group, slot] = w
    # G = D C⁻¹ Dᵀ, C the texels' total light: the solution of least C-norm spreads a flat target flat.
    inv_c = 1.0 / np.add.reduceat(w.astype(np.float64), starts)
    side = 2 * COUPLING + 1
    keys, values = [], []
    for a in range(kc):
        pa, wa = pad_p[:, a], pad_w[:, a]
        for b in range(kc):
            pb, wb = pad_p[:, b], pad_w[:, b]
            ok = (pa >= 0) & (pb >= 0)
            ya, xa = np.divmod(pa[ok], cw)
            yb, xb = np.divmod(pb[ok], cw)
            dy, dx = yb - ya, xb - xa
            near = (np.abs(dy) <= COUPLING) & (np.abs(dx) <= COUPLING)
            keys.append(((dy[near] + COUPLING) * side + dx[near] + COUPLING) * p_all + pa[ok][near])
            values.append((wa[ok] * wb[ok] * inv_c[ok])[near])
    bands = np.bincount(np.concatenate(keys), np.concatenate(values), minlength=side * side * p_all)
    return bands.reshape(side * side, ch, cw)


class _Bands:
    """``G(p, p + (dy, dx))`` as an image for any offset (zero beyond :data:`COUPLING`)."""

    def __init__(self, bands: np.ndarray) -> None:
        self.bands = bands
        self.zero = np.zeros(bands.shape[1:])

    def __call__(self, dy: int, dx: int) -> np.ndarray:
        if abs(dy) > COUPLING or abs(dx) > COUPLING:
            return self.zero
        return self.bands[(dy + COUPLING) * (2 * COUPLING + 1) + dx + COUPLING]


def solve_batched(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``x`` with ``a @ x = b`` for a batch of small systems (``a``: (..., n, n), ``b``: (..., n, k)), by Gaussian
    elimination with partial pivoting vectorised over the batch, in float64.

    ``np.linalg.solve`` hands each system to LAPACK one at a time, and a threaded OpenBLAS wakes its threads for
    every 9 × 9 system: on 2 busy cores that took 5–50 s for the 27 648 systems of a 192 × 144 camera, against
    0.1 s here (0.03 s with OpenBLAS held to one thread, which an extension cannot set once numpy is loaded).
    :class:`numpy.linalg.LinAlgError` when a system is singular, as ``np.linalg.solve``."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    n, k = a.shape[-1], b.shape[-1]
    batch = a.shape[:-2]
    # (row, column, system): each step below is one vector operation over every system
    m = np.ascontiguousarray(np.moveaxis(np.concatenate([a, b], axis=-1).reshape(-1, n, n + k), 0, -1))
    systems = np.arange(m.shape[-1])
    for c in range(n):
        pivot = c + np.argmax(np.abs(m[c:, c]), axis=0)
        swap = pivot != c
        if swap.any():
            s, p = systems[swap], pivot[swap]
            row = m[c][:, s].copy()
            m[c][:, s] = m[p, :, s].T
            m[p, :, s] = row.T
        if not np.all(m[c, c]):
            raise np.linalg.LinAlgError("Singular matrix")
        m[c + 1:, c:] -= (m[c + 1:, c] / m[c, c])[:, None] * m[c, c:][None]
    x = np.empty((n, k, m.shape[-1]))
    for i in range(n - 1, -1, -1):
        x[i] = (m[i, n:] - np.einsum("jp,jkp->kp", m[i, i + 1:n], x[i + 1:])) / m[i, i]
    return np.moveaxis(x, -1, 0).reshape(*batch, n, k)


def build_inverse(op: TransportOperator, progress: Progress | None = None) -> ApproximateInverse:
    """``M`` for the operator's direct part (module doc), channel by channel."""
    say = progress or quiet
    t0 = time.perf_counter()
    cw, ch = op.camera_size
    g2_side = 4 * STENCIL + 1
    offs = ApproximateInverse.offsets()
    n_st = len(offs)
    weight = np.zeros((ch * cw, n_st, 3), np.float32)
    conditioned = []
    for c in range(3):
        say(f"approximate inverse: channel {c + 1}/3", c / 3)
        g = _coupling_bands(op, c)
        g_at = _Bands(g)
        # G²(p, p + o) = Σ_o1 G(p, p + o1) G(p + o1, p + o) for |o| ≤ 2·STENCIL.
        g2 = np.zeros((g2_side, g2_side, ch, cw))
        r2 = 2 * STENCIL
        for oy in range(-r2, r2 + 1):
            for ox in range(-r2, r2 + 1):
                acc = np.zeros((ch, cw))
                for ay in range(-COUPLING, COUPLING + 1):
                    for ax in range(-COUPLING, COUPLING + 1):
                        by, bx = oy - ay, ox - ax
                        if abs(by) > COUPLING or abs(bx) > COUPLING:
                            continue
                        acc += g_at(ay, ax) * _shift(g_at(by, bx), ay, ax)
                g2[oy + r2, ox + r2] = acc
        # Column j of M over N_j = j + offs: (G²[N_j, N_j] + ridge) m = G[N_j, j].
        h = np.zeros((ch, cw, n_st, n_st))
        rhs = np.zeros((ch, cw, n_st))
        for i, (ay, ax) in enumerate(offs):
            rhs[..., i] = _shift(g_at(-ay, -ax), ay, ax)  # G(j + a, j)
            for k2, (by, bx) in enumerate(offs):
                h[..., i, k2] = _shift(g2[by - ay + r2, bx - ax + r2], ay, ax)  # G²(j + a, j + b)
        diag = np.einsum("...ii->...i", h)
        scale = np.maximum(diag.mean(axis=-1), 1e-12)
        h += (RIDGE * scale)[..., None, None] * np.eye(n_st)
        m = solve_batched(h, rhs[..., None])[..., 0]  # (ch, cw, 9): column j's values at j + a
        lit = g_at(0, 0) > 0
        m[~lit] = 0.0
        conditioned.append(float(np.mean(lit)))
        # Stored per receiving pixel p: weight[p, a] = m_{p − a}[a].
        for i, (ay, ax) in enumerate(offs):
            weight[:, i, c] = _shift(m[..., i], -ay, -ax).ravel()
    inv = ApproximateInverse((cw, ch), tuple(op.input_size), weight)
    inv.report = {"format": FORMAT, "version": VERSION, "stencil": f"{2 * STENCIL + 1}x{2 * STENCIL + 1}",
                  "coupling_radius": COUPLING, "ridge": RIDGE, "pixels_lit": round(float(np.mean(conditioned)), 4),
                  "seconds": round(time.perf_counter() - t0, 2), "megabytes": round(inv.nbytes / 2 ** 20, 1)}
    say("approximate inverse ready", 1.0)
    return inv


def deblur_taps(sigma: float, ridge: float = DEBLUR_RIDGE) -> np.ndarray:
    """A one-dimensional regularised inverse ``h`` of :func:`gaussian_taps` with as many taps: ``h`` minimises
    ``‖g * h − δ‖² + ridge ‖h‖²``, scaled to sum to 1 so a flat input stays flat. ``h ⊗ h`` undoes ``B`` up to the
    frequencies the ridge gives up (where the blur leaves less than about √ridge of the light), so one separable
    pass stands for the deblur a solve through ``T B`` would find."""
    g = gaussian_taps(sigma).astype(np.float64)
    n = len(g)
    conv = np.zeros((2 * n - 1, n))
    for j in range(n):
        conv[j:j + n, j] = g
    e = np.zeros(2 * n - 1)
    e[n - 1] = 1.0
    h = np.linalg.solve(conv.T @ conv + ridge * np.eye(n), conv.T @ e)
    return (h / h.sum()).astype(np.float32)


class LensBlurBox:
    """The projector lens's Gaussian blur ``B`` (``sigma`` texels) around the active texels of ``view``: the
    unknowns of a solve through ``T B`` are the texels of the box that bounds the active ones grown by the blur's
    reach (every texel whose light the blur carries onto an active one), as an image, row by row and three channels
    a texel like the compact vector.

    The blur itself is OpenCV's separable filter on that image (zero beyond it, as ``lens_blur``), between Dr.Jit
    arrays: on the CPU's backend the image is read in place. Why not Dr.Jit gathers, as the operator's own: a
    gather per tap cost 8–10 ms a pass at 800×600 (the box's 344 000 texels, 7 taps), the filter 2 ms with both
    copies; the active texels go in and out of the box by one scatter or gather."""

    def __init__(self, view: TransportRows, sigma: float) -> None:
        self._dr, self._float, self._uint = view._dr, view._float, view._uint
        self.sigma = float(sigma)
        iw, ih = view.op.input_size
        self._g = gaussian_taps(self.sigma)
        self._h = deblur_taps(self.sigma)
        r = len(self._g) // 2
        ty, tx = np.divmod(np.asarray(view.texels, np.int64), iw)
        x0, y0 = max(int(tx.min(initial=0)) - r, 0), max(int(ty.min(initial=0)) - r, 0)
        x1, y1 = min(int(tx.max(initial=0)) + r + 1, iw), min(int(ty.max(initial=0)) + r + 1, ih)
        self.size = (x1 - x0, y1 - y0)
        bw, bh = self.size
        by, bx = np.divmod(np.arange(bw * bh, dtype=np.int64), bw)
        #: the unknowns: the box's texels (flat input indices), row by row
        self.texels = (by + y0) * iw + bx + x0
        at = (ty - y0) * bw + (tx - x0)  # each active texel's place in the box
        self._at3 = self._uint((at[:, None] * 3 + np.arange(3)).ravel().astype(np.uint32))

    def _filter(self, box: Any, taps: np.ndarray) -> Any:
        bw, bh = self.size
        image = np.asarray(box, np.float32).reshape(bh, bw, 3)
        return self._float(cv2.sepFilter2D(image, -1, taps, taps, borderType=cv2.BORDER_CONSTANT).ravel())

    def embed(self, active: Any) -> Any:
        """The box image (flat) holding the active texels' values ``active`` (compact, flat), zero elsewhere."""
        bw, bh = self.size
        out = self._dr.zeros(self._float, bw * bh * 3)
        self._dr.scatter(out, active, self._at3)
        return out

    def to_active(self, box: Any) -> Any:
        """``B z`` on the active texels (compact, flat) of the box image ``z``: the light the lens lets fall there."""
        return self._dr.gather(self._float, self._filter(box, self._g), self._at3)

    def from_active(self, active: Any, deblur: bool = False) -> Any:
        """The box image ``B a`` (``Bᵀ = B``: zero borders keep it symmetric) of values ``a`` on the active texels,
        or with ``deblur`` its regularised inverse ``H a`` (:func:`deblur_taps`)."""
        return self._filter(self.embed(active), self._h if deblur else self._g)


class RealtimeView:
    """The real-time solve (module doc) on one display area of one projector's operator ``view`` (``T`` on the
    area's rows), for the inverse ``inverse`` and the open loop's per-pixel ``gain`` on the rows (None: 1).

    Every array of a frame stays a Dr.Jit array from the target's upload to the native frame's download, so
    the solve is a handful of fused kernels on whichever backend the calibration's variant runs (LLVM on the
    CPU's cores, CUDA on a GPU), with no numpy pass over a row or texel in between. The interreflected light is
    computed once a frame, from the previous frame's answer, and held through the refinement step: it is
    smooth, changes slowly, and is the costliest part of ``T`` (a product with every block's response).

    A :class:`~.transport.BlurredRows` view (``T B``, the projector lens's blur that ``--effects defocus`` holds
    in stage C's solve) is solved through the blur: the one-pass inverse gives the light wanted on the active
    texels, one separable pass of the blur's regularised inverse (:func:`deblur_taps`) turns it into the input to
    send on the box around them (:class:`LensBlurBox`), and the refinement steps run on ``T B`` (forward and
    adjoint through the blur, as stage C's). The interreflection is then taken from the light after the blur."""

    def __init__(self, view: TransportRows | BlurredRows, inverse: ApproximateInverse,
                 gain: np.ndarray | None = None) -> None:
        self.blur: LensBlurBox | None = None
        if isinstance(view, BlurredRows):
            self.blur = LensBlurBox(view.view, view.sigma)
            view = view.view
        if not inverse.fits(view.op):
            raise InverseError("the approximate inverse is for another camera or input size than this "
                               "calibration's operator: run procam precompute --live --force")
        self.view = view
        dr, fl = view._dr, view._float
        self._dr, self._float = dr, fl
        rows = view.rows
        n_rows = len(rows)
        cw, ch = view.op.camera_size
        y, x = np.divmod(rows, cw)
        offs = ApproximateInverse.offsets()
        # M's stencil as a gather over the rows: taps on pixels outside them read nothing (no light wanted).
        where = np.full(cw * ch, -1, np.int64)
        where[rows] = np.arange(n_rows)
        src = np.zeros((n_rows, len(offs)), np.int64)
        w = np.zeros((n_rows, len(offs), 3), np.float32)
        for a, (dy, dx) in enumerate(offs):
            yy, xx = y - dy, x - dx
            ok = (yy >= 0) & (yy < ch) & (xx >= 0) & (xx < cw)
            src[:, a] = np.where(ok, where[np.where(ok, yy * cw + xx, 0)], -1)
            w[:, a] = np.where((src[:, a] >= 0)[:, None], inverse.weight[rows, a], 0.0)
        self._taps = len(offs)
        self._st_src, self._st_live = self._index(src)
        self._st_w = fl(np.ascontiguousarray(np.transpose(w, (0, 2, 1))).ravel())
        # C⁻¹ of A = C⁻¹ Dᵀ M: each active texel's total direct light over the whole camera.
        op = view.op
        flat_w = op.weight.reshape(-1, 3)
        sums = np.stack([np.bincount(op.index.ravel(), flat_w[:, c], minlength=op.input_size[0] * op.input_size[1])
                         for c in range(3)], axis=1)[view.texels]
        self._inv_c = fl((1.0 / np.maximum(sums, 1e-12)).astype(np.float32).ravel())
        self._indirect_parts()
        gain_np = np.ones((n_rows, 3), np.float32) if gain is None else np.asarray(gain, np.float32)
        self.gain = fl(gain_np.ravel())
        self._gain_np = gain_np
        self.row_sums = dr.maximum(self.gain * fl(np.ascontiguousarray(view.row_ones, np.float32).ravel()), 1e-3)
        col = self._adjoint_direct(self.gain)
        if self.blur is not None:
            col = self.blur.from_active(col)
        self.col_sums = dr.maximum(col, 1e-3)
        #: the texels of an answer (:meth:`solve`): the active ones, or with a lens blur the box around them
        self.texels = view.texels if self.blur is None else self.blur.texels
        self._held: dict[tuple[float, ...], Any] = {}  # :meth:`hold`'s colours over the answer's texels
        self._prev = dr.zeros(fl, len(view.texels) * 3)  # the light on the active texels of the previous answer
        self._warm = False
        self._ind = dr.zeros(fl, n_rows * 3)
        dr.eval(self.row_sums, self.col_sums, self._prev, self._ind)

    def _index(self, src: np.ndarray) -> tuple[Any, Any]:
        """(rows, taps) sources (−1: none) as Dr.Jit indices laid out (row, channel, tap), and which are live."""
        spread = np.maximum(src, 0)[:, None, :] * 3 + np.arange(3)[None, :, None]
        live = np.repeat((src >= 0)[:, None, :], 3, axis=1)
        return self.view._uint(spread.ravel().astype(np.uint32)), self.view._bool(live.ravel())

    def _indirect_parts(self) -> None:
        """The operator's indirect part as gathers over the compact input: block sums over each block's run of
        active texels (the inactive ones are dark in a live show), the product with every block's low-resolution
        response, and the existing upsampling to the rows."""
        view = self.view
        self._nb = view._nb
        if not self._nb:
            return
        runs, starts, counts = view._runs, view._run_starts, view._run_counts
        longest = int(counts.max(initial=1))
        src = np.full((self._nb, longest), -1, np.int64)
        j = np.arange(longest)
        src[runs] = np.where(j[None, :] < counts[:, None], starts[:, None] + j[None, :], -1)
        self._blk_len = longest
        self._blk_src, self._blk_live = self._index(src)
        self._blk_size = self._float(np.repeat(view._block_sizes, 3).astype(np.float32))
        responses = view._responses  # (channel, used low pixel, block)
        used, nb = responses.shape[1], responses.shape[2]
        # low[u, c] = Σ_b R[c, u, b] · mean[b, c], laid out (u, c, b)
        self._resp = self._float(np.ascontiguousarray(responses.transpose(1, 0, 2)).ravel())
        b = np.arange(nb)
        self._resp_src = view._uint(np.broadcast_to(b[None, None, :] * 3 + np.arange(3)[None, :, None],
                                                    (used, 3, nb)).ravel().astype(np.uint32))

    def _direct(self, zc: Any) -> Any:
        """``D z`` on the rows (flat, rows × 3) for a compact Dr.Jit ``zc``."""
        return self.view.direct(zc)

    def _adjoint_direct(self, r: Any) -> Any:
        """``Dᵀ r`` on the active texels (flat, texels × 3) for a Dr.Jit ``r`` on the rows."""
        v, dr = self.view, self._dr
        return dr.block_sum(dr.gather(self._float, r, v._col_src) * v._col_w, v._kc)

    def _indirect(self, zc: Any) -> Any:
        """The interreflected light on the rows of a compact Dr.Jit ``zc`` (zero without an indirect part)."""
        dr, fl, v = self._dr, self._float, self.view
        if not self._nb:
            return dr.zeros(fl, len(v.rows) * 3)
        sums = dr.block_sum(dr.gather(fl, zc, self._blk_src, self._blk_live), self._blk_len)
        means = sums / self._blk_size
        dr.eval(means)
        low = dr.block_sum(dr.gather(fl, means, self._resp_src) * self._resp, self._nb)
        dr.eval(low)
        return dr.block_sum(dr.gather(fl, low, v._low_src) * v._low_w, 4)

    def solve(self, target: np.ndarray, theta: np.ndarray | None = None, steps: int = 1) -> Any:
        """The compact input (a Dr.Jit array, :attr:`texels` × 3 flat) for the rows' ``target`` and θ (the camera
        sees ``g·T z − θ``, or ``g·T B z − θ`` through a lens blur): the previous frame's interreflection taken off
        the light wanted, ``A`` applied and the box clipped (with a lens blur: its regularised inverse applied and
        clipped again), then ``steps`` SIRT steps with that interreflection held."""
        dr, fl = self._dr, self._float
        want = fl(np.ascontiguousarray(target if theta is None else target + theta, np.float32).ravel())
        if not self._warm:
            # The first frame has no previous answer to take its interreflection from: solve it first for that
            # (1.9 dB below the next frames at 1600×1200 on the lab's curve without this). Each solve takes the
            # interreflection of the one before, so the level settles by a damped oscillation: with one such solve
            # the first frames' mean level swung by 0.007, 0.0015, 0.0003 on the lab's curve at 1920×1080, a
            # flicker of the whole picture the real camera saw (scripts/bench_live_show.py).
            self._warm = True
            for _ in range(FIRST_FRAME_SOLVES):
                self.solve(target, theta, steps)
        ind = self._indirect(self._prev)
        direct = want / dr.maximum(self.gain, 1e-3) - ind
        u = dr.block_sum(dr.gather(fl, direct, self._st_src, self._st_live) * self._st_w, self._taps)
        dr.eval(u)
        zc = dr.clip(self._adjoint_direct(u) * self._inv_c, 0.0, 1.0)
        dr.eval(zc)
        blur = self.blur
        light = zc  # the light on the active texels: the input itself without a lens blur
        if blur is not None:
            zc = dr.clip(blur.from_active(zc, deblur=True), 0.0, 1.0)
            dr.eval(zc)
        for _ in range(steps):
            light = zc if blur is None else blur.to_active(zc)
            resid = want - self.gain * (self._direct(light) + ind)
            dr.eval(resid)
            step = self._adjoint_direct(self.gain * resid / self.row_sums)
            if blur is not None:
                step = blur.from_active(step)
            zc = dr.clip(zc + step / self.col_sums, 0.0, 1.0)
            dr.eval(zc)
        # Through a lens blur the last step's light before its update stands for the answer's (interreflection is
        # smooth and slow; blurring the answer once more would cost a third of a step).
        self._prev = zc if blur is None else light
        return zc

    def hold_mask(self, texels: np.ndarray) -> Any:
        """A Dr.Jit mask over a compact input (flat, :attr:`texels` × 3) of the texels where ``texels`` (bool, one
        per answer texel) is set, for :meth:`hold`."""
        return self.view._bool(np.repeat(np.asarray(texels, bool), 3))

    def hold(self, zc: Any, mask: Any, value: tuple[float, float, float] | None) -> Any:
        """The compact ``zc`` with the texels of ``mask`` (:meth:`hold_mask`) at ``value`` (RGB; None: black)."""
        dr, fl = self._dr, self._float
        key = (0.0, 0.0, 0.0) if value is None else tuple(float(v) for v in value)
        held = self._held.get(key)
        if held is None:  # made once a colour: a live show holds the same texels every frame
            held = self._held[key] = fl(np.tile(np.asarray(key, np.float32), len(self.texels)))
        out = dr.select(mask, held, zc)
        dr.eval(out)
        return out

    def compact(self, zc: Any) -> np.ndarray:
        """A compact Dr.Jit input as numpy (:attr:`texels`, 3)."""
        return np.asarray(zc).reshape(-1, 3)

    def expand(self, zc: Any, fill: tuple[float, float, float] | None = None) -> np.ndarray:
        """The input image (input size, H×W×3) of a compact ``zc``: black beyond :attr:`texels` (``fill``: that
        colour)."""
        iw, ih = self.view.op.input_size
        out = np.zeros((ih * iw, 3), np.float32)
        if fill is not None:
            out[:] = np.asarray(fill, np.float32)
        out[self.texels] = self.compact(zc)
        return out.reshape(ih, iw, 3)

    def light(self, zc: Any) -> np.ndarray:
        """(R, 3) ``g·T z`` (``g·T B z`` through a lens blur) of the compact ``zc`` by the full operator
        (unclipped)."""
        if self.blur is not None:
            return self._gain_np * self.view.apply(lens_blur(self.expand(zc), self.blur.sigma))
        return self._gain_np * self.view.apply_compact(self.compact(zc))

    def predicted(self, zc: Any, theta: np.ndarray | None = None) -> np.ndarray:
        """(R, 3) what the full operator says the camera sees of the compact ``zc``: ``clip(g·T z − θ)``."""
        f = self.light(zc)
        return np.clip(f if theta is None else f - theta, 0.0, 1.0)


class FrameGather:
    """The projector's native frame straight from a compact input ``zc`` of ``view``: the stage-B warp's bilinear
    taps (``x = W(z)``), the texels outside ``view.texels`` (black), the frame's placement and the box clip as one
    Dr.Jit gather, instead of expanding, warping and placing in numpy (11 ms of a 36 ms frame at 800×600). Only
    the frame pixels some lit texel reaches are gathered (half of an 800×600 frame on the lab's curve); the rest
    stay black. ``texels``: the texels of the compact inputs (default: the view's active ones; a solve through a lens
    blur answers on the box around them, :attr:`RealtimeView.texels`). ``surround`` (RGB, a share of white): the
    input everywhere else, instead of black (``--surround``): the frame's input region shows it, and a tap on a
    texel outside the compact inputs reads it."""

    def __init__(self, view: TransportRows, projector: Any, warp: Any = None, texels: np.ndarray | None = None,
                 surround: tuple[float, float, float] | None = None) -> None:
        self._dr, self._float, self._uint = view._dr, view._float, view._uint
        iw, ih = projector.input_size
        fw, fh = projector.intrinsics.size
        x0, y0 = projector.input_offset
        n = iw * ih
        if warp is None or warp.is_identity:
            index, weight = np.arange(n)[None, :], np.ones((1, n), np.float32)
        else:
            d = warp.displacement("w", (iw, ih)).reshape(-1, 2)
            c = pixel_centres((iw, ih)).reshape(-1, 2)
            index, weight = bilinear_taps((iw, ih), c[:, 0] + d[:, 0], c[:, 1] + d[:, 1])
            index, weight = index.reshape(len(index), -1), weight.reshape(len(weight), -1)
        where = np.full(n, -1, np.int64)
        texels = np.asarray(view.texels if texels is None else texels, np.int64)
        where[texels] = np.arange(len(texels))
        pos = where[index]  # (taps, n): compact position of each tap's texel, −1 for a dark texel
        live = (pos >= 0) & (weight > 0)
        lit = np.flatnonzero(live.any(axis=0))  # input texels some lit texel reaches through the warp
        ty, tx = np.divmod(lit, iw)
        #: the frame pixels gathered (flat indices of the native frame), and the input texel each one shows
        self._pixels = (ty + y0) * fw + (tx + x0)
        tap_pos, tap_live = pos[:, lit].T, live[:, lit].T  # (pixels, taps)
        self._k = tap_pos.shape[1]
        self._size = (fw, fh)
        src = np.maximum(tap_pos, 0)
        self._src = [view._uint((src * 3 + c).ravel().astype(np.uint32)) for c in range(3)]
        self._live = view._bool(tap_live.ravel())
        self._w = self._float(np.where(tap_live, weight[:, lit].T, 0.0).astype(np.float32).ravel())
        #: with a surround: its light on each gathered pixel through the taps on texels outside the compact inputs,
        #: per channel, and the frame pixels of the input region (the rest of the native frame stays black)
        self._surround = None if surround is None or not any(surround) else np.asarray(surround, np.float32)
        self._dead: list[Any] = []
        if self._surround is not None:
            dead = np.where(tap_live, 0.0, weight[:, lit].T).sum(axis=1).astype(np.float32)
            self._dead = [self._float(dead * self._surround[c]) for c in range(3)]
            ry, rx = np.mgrid[y0:y0 + ih, x0:x0 + iw]
            self._region = (ry * fw + rx).ravel()

    def _channels(self, zc: Any) -> list[Any]:
        dr = self._dr
        values = zc if isinstance(zc, self._float) else self._float(np.ascontiguousarray(zc, np.float32).ravel())
        sums = [dr.block_sum(dr.gather(self._float, values, src, self._live) * self._w, self._k) for src in self._src]
        if self._dead:
            sums = [v + d for v, d in zip(sums, self._dead)]
        return [dr.clip(v, 0.0, 1.0) for v in sums]

    def __call__(self, zc: Any) -> np.ndarray:
        """The native frame (H×W×3 floats in [0, 1]) of a compact input (a Dr.Jit array or numpy (texels, 3))."""
        fw, fh = self._size
        out = np.zeros((fh * fw, 3), np.float32)
        if self._surround is not None:
            out[self._region] = self._surround
        out[self._pixels] = np.stack([np.asarray(v) for v in self._channels(zc)], axis=1)
        return out.reshape(fh, fw, 3)

    def levels(self, zc: Any) -> np.ndarray:
        """The native frame as the 8-bit levels a projector window shows, RGBX (H×W×4 uint8, the fourth byte 255,
        no transfer curve): packed into one 32-bit word a pixel on the Dr.Jit side, so that neither a float
        conversion (4 ms of a frame's 33 at 800×600 in numpy) nor a repacking stands between the solve and SDL."""
        dr, u32 = self._dr, self._uint
        r, g, b = (u32(dr.round(v * 255.0)) for v in self._channels(zc))
        packed = r | (g << 8) | (b << 16) | 0xFF000000
        fw, fh = self._size
        out = np.full(fh * fw, 0xFF000000, np.uint32)
        if self._surround is not None:
            sr, sg, sb = (int(v) for v in np.rint(np.clip(self._surround, 0.0, 1.0) * 255.0))
            out[self._region] = sr | (sg << 8) | (sb << 16) | 0xFF000000
        out[self._pixels] = np.asarray(packed)
        return out.view(np.uint8).reshape(fh, fw, 4)


__all__ = ["ApproximateInverse", "FrameGather", "InverseError", "LensBlurBox", "RealtimeView", "build_inverse",
           "building_bytes", "deblur_taps"]
