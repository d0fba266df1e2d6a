"""The light-transport operator of one calibration: ``f̂(z) ≈ T z``, precomputed once, so stage C needs no renders.

With the surface Lambertian and nothing clamped, the simulated camera image is
linear in the virtual input ``z``; and for a fixed sampler seed Mitsuba's
estimate is linear too, because no sample's path depends on the projector's
texture (the projector is a delta light, looked up, never sampled by
texture). ``T`` has two parts:

**Direct, exact and sparse.** A camera pixel sees the few input texels whose
light lands in its footprint (the texels under it and the bilinear lookup's
neighbours). ``T`` is read off renders of *impulse lattices*: every s-th texel
white in x and y, one render per lattice offset (s² renders, direct light,
unclamped, all with the same seed). Each camera pixel's value in a lattice
render comes from the one lattice node nearest to where it looks in the
input (the ray-cast camera → input correspondence), because s is chosen
wider than the widest footprint; that value is the pixel's weight for that
node. With the seed shared, ``T z`` equals the direct render of ``z`` at that
seed for every ``z`` (up to pixels whose footprint is wider than s/2, counted
and reported).

**Indirect, compact.** Interreflected light is smooth across the camera: the
input is cut into B × B blocks, each block is rendered lit (one bounce) and
unlit-direct at a quarter of the camera's resolution, and the difference is
that block's indirect response. ``T z`` adds, for every block, its mean input
times its response, upsampled.

Stage C on the operator (``stages/solve_transport.py``, schedule ``transport``)
needs ``T z`` and ``Tᵀ r`` only: sparse gathers and scatters, no Mitsuba.
"""

from __future__ import annotations

import math
import os
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ..errors import ProCamError
from ..progress import Cancel, Progress, quiet
from ..render import backend
from ..render.forward import ForwardModel
from ..render.raycast import first_hits

#: Entries kept per camera pixel (the largest; a footprint rarely spans more than 4 × 4 texels).
MAX_ENTRIES = 16
#: Samples per pixel of the direct renders. Each entry of ``T`` is the share of a pixel's samples that land in a
#: texel's bilinear reach, so few samples leave it coarse at the finest scale: against the lab's captures of texel
#: noise, 16 left a mismatch that fits a blur of σ 0.3 camera px, 64 none (``scripts/bench_stacked_error.py
#: --sources``), for 1.5× the build time.
DIRECT_SPP = 64
#: Lattice spacing bounds (renders = spacing²).
MIN_SPACING, MAX_SPACING = 3, 9
FORMAT, VERSION = "procam-transport", 1


class TransportError(ProCamError):
    """The light-transport operator cannot be built, read or used with this calibration."""


class TransportMemoryError(TransportError):
    """Building the light-transport operator would need more memory than this machine has free."""


def building_bytes(camera_size: tuple[int, int], spacing: int = MAX_SPACING, bounces: int = 1, blocks: int = 8,
                   indirect_scale: float = 0.25) -> int:
    """The most memory building ``T`` takes: every lattice render's entry for every camera pixel (index and
    three weights) before the strongest ``MAX_ENTRIES`` are kept, those kept, and the indirect responses."""
    cw, ch = camera_size
    pixels = cw * ch
    direct = pixels * spacing * spacing * 16 + pixels * MAX_ENTRIES * 16
    low = max(2, round(cw * indirect_scale)) * max(2, round(ch * indirect_scale))
    return int(direct + (blocks * blocks * low * 12 if bounces else 0))


def free_bytes() -> int | None:
    """Memory this machine can give now (Linux's MemAvailable, else the free pages), None when it cannot say."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def check_memory(camera_size: tuple[int, int], spacing: int = MAX_SPACING, bounces: int = 1) -> None:
    """A :class:`TransportMemoryError` saying how much building ``T`` needs when that is more than 80 % of the
    memory free now."""
    need, free = building_bytes(camera_size, spacing, bounces), free_bytes()
    if free is not None and need > 0.8 * free:
        cw, ch = camera_size
        raise TransportMemoryError(f"building the light-transport operator of a {cw}×{ch} camera needs about "
                                   f"{need / 2 ** 30:.1f} GiB and {free / 2 ** 30:.1f} GiB are free: free memory, or "
                                   "compensate with --schedule fast (renders instead of the operator)")


@dataclass
class TransportOperator:
    """``T`` of one calibration (module doc). Images are camera-size H×W×3, inputs input-size H×W×3."""

    camera_size: tuple[int, int]
    input_size: tuple[int, int]
    index: np.ndarray  # (P, K) int32: input texel (row * width + column) of each entry of each camera pixel
    weight: np.ndarray  # (P, K, 3) float32: the entries
    blocks: tuple[int, int]  # indirect blocks across and down the input
    indirect: np.ndarray  # (blocks, h, w, 3) float32: each block's indirect response at low resolution
    report: dict[str, Any] = field(default_factory=dict)
    _all: TransportRows | None = field(default=None, repr=False, compare=False)

    # -- the operator ------------------------------------------------------------------------------------------

    def _block_edges(self) -> tuple[np.ndarray, np.ndarray]:
        """First input row of each block row and first column of each block column (blocks are contiguous)."""
        iw, ih = self.input_size
        bx, by = self.blocks
        return (np.searchsorted(np.arange(ih) * by // ih, np.arange(by)),
                np.searchsorted(np.arange(iw) * bx // iw, np.arange(bx)))

    def _block_sizes(self) -> np.ndarray:
        """(blocks,) texels in each block, row-major like the blocks."""
        iw, ih = self.input_size
        rows, cols = self._block_edges()
        return (np.diff(np.append(rows, ih))[:, None] * np.diff(np.append(cols, iw))[None, :]).ravel()

    def _block_sums(self, z: np.ndarray) -> np.ndarray:
        """(blocks, 3) sum of the input over each block, by sums over contiguous row and column runs."""
        iw, ih = self.input_size
        rows, cols = self._block_edges()
        sums = np.add.reduceat(np.add.reduceat(np.asarray(z).reshape(ih, iw, 3), rows, axis=0, dtype=np.float64),
                               cols, axis=1)
        return sums.reshape(-1, 3)

    def block_of(self, texels: np.ndarray) -> np.ndarray:
        """The indirect block (row-major) of each flat input texel index."""
        iw, ih = self.input_size
        bx, by = self.blocks
        row, col = np.divmod(np.asarray(texels, np.int64), iw)
        return (row * by // ih) * bx + col * bx // iw

    def _spread(self, per_block: np.ndarray) -> np.ndarray:
        """(blocks, 3) values → input size, each block's value over its texels."""
        iw, ih = self.input_size
        rows, cols = self._block_edges()
        grid = np.asarray(per_block, np.float32).reshape(len(rows), len(cols), 3)
        return np.repeat(np.repeat(grid, np.diff(np.append(rows, ih)), axis=0), np.diff(np.append(cols, iw)), axis=1)

    def direct(self, z: np.ndarray) -> np.ndarray:
        """The direct part of ``T z`` alone (camera size), in plain numpy."""
        flat = np.asarray(z, np.float32).reshape(-1, 3)
        out = np.einsum("pkc,pkc->pc", self.weight, flat[self.index])
        cw, ch = self.camera_size
        return out.reshape(ch, cw, 3)

    def _everywhere(self) -> TransportRows:
        if self._all is None:
            cw, ch = self.camera_size
            self._all = self.rows(np.arange(cw * ch))
        return self._all

    def apply(self, z: np.ndarray) -> np.ndarray:
        """``T z``: the simulated camera image of ``z`` (unclamped)."""
        cw, ch = self.camera_size
        return self._everywhere().apply(z).reshape(ch, cw, 3)

    def adjoint(self, r: np.ndarray) -> np.ndarray:
        """``Tᵀ r`` for a camera-size image ``r``: what each input texel's value does to ⟨r, T z⟩."""
        return self._everywhere().adjoint(np.asarray(r, np.float32).reshape(-1, 3))

    def rows(self, rows: np.ndarray, variant: str | None = None) -> TransportRows:
        """``T`` restricted to some camera pixels (a display area): cheaper, for a solver that looks only there."""
        return TransportRows(self, np.asarray(rows, np.int64), variant)

    # -- storage ---------------------------------------------------------------------------------------------

    def arrays(self) -> dict[str, np.ndarray]:
        return {"index": self.index, "weight": self.weight, "indirect": self.indirect,
                "camera_size": np.asarray(self.camera_size), "input_size": np.asarray(self.input_size),
                "blocks": np.asarray(self.blocks)}

    @property
    def nbytes(self) -> int:
        return int(self.index.nbytes + self.weight.nbytes + self.indirect.nbytes)

    @staticmethod
    def from_arrays(data: Any, report: dict[str, Any] | None = None) -> TransportOperator:
        try:
            op = TransportOperator(tuple(int(v) for v in data["camera_size"]),
                                   tuple(int(v) for v in data["input_size"]),
                                   np.asarray(data["index"], np.int32), np.asarray(data["weight"], np.float32),
                                   tuple(int(v) for v in data["blocks"]), np.asarray(data["indirect"], np.float32),
                                   dict(report or {}))
        except (KeyError, ValueError, TypeError) as exc:
            raise TransportError(f"the stored transport operator is incomplete ({exc}); run procam precompute "
                                 "again") from None
        wrong = op._inconsistency()
        if wrong:
            raise TransportError(f"the stored transport operator is damaged ({wrong}); run procam precompute again "
                                 "with --force")
        return op

    def _inconsistency(self) -> str:
        """What in the arrays cannot be an operator ("" when nothing): the gathers index with them unchecked, so an
        entry outside the input (a damaged or edited file) would read outside the array, and a weight that is no
        number would spread NaN through every solve."""
        (cw, ch), (iw, ih), (bx, by) = self.camera_size, self.input_size, self.blocks
        if min(cw, ch, iw, ih) < 1 or min(bx, by) < 0 or (bx * by == 0 and (bx, by) != (0, 0)):
            return "a size below 1 or a block count below 0"  # (0, 0) blocks: direct light only (bounces 0)
        p = cw * ch
        if self.index.ndim != 2 or self.index.shape[0] != p or self.weight.shape != (*self.index.shape, 3):
            return f"entries of shape {self.index.shape} and {self.weight.shape} for {p} camera pixels"
        if self.index.size and (int(self.index.min()) < 0 or int(self.index.max()) >= iw * ih):
            return f"an entry outside the {iw}×{ih} input"
        if self.indirect.ndim != 4 or self.indirect.shape[0] != bx * by or self.indirect.shape[3] != 3:
            return f"indirect responses of shape {self.indirect.shape} for {bx}×{by} blocks"
        if not (np.isfinite(self.weight).all() and np.isfinite(self.indirect).all()) or float(self.weight.min(
                initial=0.0)) < 0:
            return "a weight that is negative or no number"
        return ""


def _taps(n_out: int, n_in: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Linear interpolation between pixel centres (edges held): for each output, its two inputs and the second's
    weight."""
    pos = np.clip((np.arange(n_out) + 0.5) * n_in / n_out - 0.5, 0.0, n_in - 1.0)
    lo = np.floor(pos).astype(np.int64)
    return lo, np.minimum(lo + 1, n_in - 1), (pos - lo).astype(np.float32)


def _regroup(keys: np.ndarray, groups: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Entries regrouped by key (0 … groups − 1) for a gather padded to the largest group: the entries' order,
    each ordered entry's key and slot within its group, and that largest group's size (at least 1)."""
    order = np.argsort(keys, kind="stable")
    counts = np.bincount(keys, minlength=groups)
    slot = np.arange(len(order)) - np.repeat(np.cumsum(counts) - counts, counts)
    return order, keys[order], slot, max(1, int(counts.max(initial=0)))


@dataclass
class TransportRows:
    """``T`` restricted to the camera pixels ``rows`` (flat indices): ``apply`` gives (R, 3), ``adjoint`` takes it.

    A solver works on the *active* texels only (:attr:`texels`: those whose
    direct light reaches one of the rows), in a compact (A, 3) vector
    (``compact``/``expand``): the other texels reach the rows through
    interreflection alone, as part of their block's mean, so their block sums
    are held fixed (``fixed_sums``). At full resolution a display area's rows see
    about half the input, and every elementwise step of a solver halves with it.
    The active texels are ordered by indirect block, so block sums are sums over
    contiguous runs.

    Both directions are Dr.Jit gathers summed in fixed-size blocks: ``apply`` over
    each row's entries, ``adjoint`` over each texel's (the entries regrouped by
    texel once, here), and the indirect part's upsampling over each row's four
    low-resolution neighbours. (10× numpy's speed on 2 cores, measured at 120 000
    rows × 16 entries: 9 ms against 90 ms for numpy's gather alone; an atomic
    scatter-add adjoint took 31 ms.) Block sums and the low-resolution products stay numpy."""

    op: TransportOperator
    rows: np.ndarray
    variant: str | None = None

    def __post_init__(self) -> None:
        import drjit as dr

        self._dr = dr
        mi = backend.mitsuba(self.variant or backend.default_variant())
        self._float, self._uint, self._bool, k = mi.Float, mi.UInt32, mi.Bool, self.op.index.shape[1]
        iw, ih = self.op.input_size
        index, weight = self.op.index[self.rows], self.op.weight[self.rows]
        self._k = k
        self._row_ones: np.ndarray | None = None
        self._jit: Any = None  # its steps on the device (stages/solve_jit.py), made on first use
        flat_w = weight.reshape(-1, 3)
        live = np.flatnonzero(flat_w.max(axis=1) > 0)  # unused entries point at texel 0 with weight 0
        src = index.ravel().astype(np.int64)[live]
        texels = np.unique(src)
        bx, by = self.op.blocks
        self._nb = bx * by
        if self._nb:
            block = self.op.block_of(texels)
            order = np.lexsort((texels, block))
            texels, block = texels[order], block[order]
            self._block_sizes = self.op._block_sizes().astype(np.float64)
            counts = np.bincount(block, minlength=self._nb)
            self._runs = np.flatnonzero(counts)  # blocks holding active texels
            self._run_starts = (np.cumsum(counts) - counts)[self._runs]
            self._run_counts = counts[self._runs]
        #: the active texels (flat input indices), ordered by indirect block
        self.texels = texels
        where = np.zeros(iw * ih, np.int64)
        where[texels] = np.arange(len(texels))
        compact = where[index]  # unused entries: weight 0, any position
        # Only the rows this projector lights directly are gathered: with several projectors on one display area
        # each lights a part of the rows, and a row it does not light would sum k zero products. (A NaN weight, a
        # damaged operator, keeps its row: the solve must see the NaN and stop.)
        lit = np.flatnonzero((weight != 0).reshape(len(self.rows), -1).any(axis=1))
        # Entries laid out (pixel, channel, entry) so that each output value is a block of k consecutive products.
        self._src = mi.UInt32((compact[lit][:, None, :] * 3 + np.arange(3)[None, :, None]).ravel().astype(np.uint32))
        self._w = mi.Float(np.ascontiguousarray(np.transpose(weight[lit], (0, 2, 1))).ravel())
        self._spread: tuple[Any, Any] | None = None
        if len(lit) < len(self.rows):
            # the lit rows' values put back among all the rows, zero on the others
            pos = np.zeros(len(self.rows), np.int64)
            pos[lit] = np.arange(len(lit))
            on = np.zeros(len(self.rows), bool)
            on[lit] = True
            self._spread = (mi.UInt32((pos[:, None] * 3 + np.arange(3)[None, :]).ravel().astype(np.uint32)),
                            mi.Bool(np.repeat(on, 3)))
        # The adjoint as a gather too (atomic scatter-adds were 3× slower): entries regrouped by active texel,
        # each padded to the most entries any texel has, laid out (texel, channel, entry).
        order, pos, slot, kc = _regroup(where[src], len(texels))
        pixel = np.zeros((len(texels), kc), np.int64)
        w_col = np.zeros((len(texels), kc, 3), np.float32)
        pixel[pos, slot] = live[order] // k
        w_col[pos, slot] = flat_w[live[order]]
        self._kc = kc
        self._col_src = mi.UInt32((pixel[:, None, :] * 3 + np.arange(3)[None, :, None]).ravel().astype(np.uint32))
        self._col_w = mi.Float(np.ascontiguousarray(np.transpose(w_col, (0, 2, 1))).ravel())
        if self._nb:
            # Each row's four low-resolution neighbours and their bilinear weights (the upsampling as a gather).
            lh, lw = self.op.indirect.shape[1:3]
            cw, ch = self.op.camera_size
            ylo, yhi, fy = _taps(ch, lh)
            xlo, xhi, fx = _taps(cw, lw)
            y, x = np.divmod(self.rows, cw)
            low_index = np.stack([ylo[y] * lw + xlo[x], ylo[y] * lw + xhi[x], yhi[y] * lw + xlo[x],
                                  yhi[y] * lw + xhi[x]], axis=1)
            low_weight = np.stack([(1 - fy[y]) * (1 - fx[x]), (1 - fy[y]) * fx[x], fy[y] * (1 - fx[x]),
                                   fy[y] * fx[x]], axis=1).astype(np.float32)
            # Only the low-resolution pixels the rows read are computed, numbered 0… in ``used``.
            used, low_index = np.unique(low_index, return_inverse=True)
            low_index = low_index.reshape(-1, 4)
            self._low_src = mi.UInt32((low_index[:, None, :] * 3 + np.arange(3)[None, :, None]).ravel()
                                      .astype(np.uint32))  # (row, channel, tap)
            self._low_w = mi.Float(np.repeat(low_weight[:, None, :], 3, axis=1).ravel())
            # The upsampling's adjoint as a gather too: each used low pixel's (row, tap) pairs, padded.
            order, low, slot, kl = _regroup(low_index.ravel(), len(used))
            row_of = np.zeros((len(used), kl), np.int64)
            w_of = np.zeros((len(used), kl), np.float32)
            row_of[low, slot] = order // 4
            w_of[low, slot] = low_weight.ravel()[order]
            self._kl = kl
            self._up_src = mi.UInt32((row_of[:, None, :] * 3 + np.arange(3)[None, :, None]).ravel().astype(np.uint32))
            self._up_w = mi.Float(np.repeat(w_of[:, None, :], 3, axis=1).ravel())
            # (channel, used low pixel, block): both directions are then one batched matrix product.
            self._responses = np.ascontiguousarray(self.op.indirect.reshape(self._nb, -1, 3)[:, used]
                                                   .transpose(2, 1, 0))

    # -- the compact vector of active texels -------------------------------------------------------------------

    def compact(self, z: np.ndarray) -> np.ndarray:
        """(A, 3) values of the active texels of an input-size ``z``."""
        return np.take(np.asarray(z, np.float32).reshape(-1, 3), self.texels, axis=0)  # 3× fancy indexing's speed

    def expand(self, zc: np.ndarray, z: np.ndarray) -> np.ndarray:
        """``z`` (input size) with its active texels replaced by ``zc``."""
        out = np.array(z, np.float32).reshape(-1, 3)
        out[self.texels] = zc
        return out.reshape(np.shape(z))

    def _active_sums(self, zc: np.ndarray) -> np.ndarray:
        """(blocks, 3) sums of the active texels of each block (runs of the block-ordered compact vector)."""
        sums = np.zeros((self._nb, 3), np.float64)
        if len(zc):
            sums[self._runs] = np.add.reduceat(zc, self._run_starts, axis=0, dtype=np.float64)
        return sums

    def fixed_sums(self, z: np.ndarray) -> np.ndarray:
        """(blocks, 3) sums of the *inactive* texels of each block of ``z``: what a solver on the active texels
        holds fixed. Zero without an indirect part."""
        if not self._nb:
            return np.zeros((0, 3))
        return self.op._block_sums(z) - self._active_sums(self.compact(z))

    @property
    def row_ones(self) -> np.ndarray:
        """(R, 3) ``T 1``: each row's light from a white input (SIRT's row sums), computed once."""
        if self._row_ones is None:
            iw, ih = self.op.input_size
            self._row_ones = self.apply(np.ones((ih, iw, 3), np.float32))
        return self._row_ones

    # -- the operator ------------------------------------------------------------------------------------------

    def apply_compact(self, zc: np.ndarray, fixed: np.ndarray | None = None) -> np.ndarray:
        """(R, 3) ``T z`` where ``z`` holds ``zc`` on the active texels and block sums ``fixed`` elsewhere
        (None: zero)."""
        return np.asarray(self.apply_pending(zc, fixed)).reshape(-1, 3)

    def apply_pending(self, zc: np.ndarray, fixed: np.ndarray | None = None) -> Any:
        """:meth:`apply_compact` as a Dr.Jit array not yet evaluated, so that several views' run in one launch
        (:func:`apply_together`)."""
        dr = self._dr
        out = self.direct(self._float(np.ascontiguousarray(zc, dtype=np.float32).ravel()))
        if self._nb:
            sums = self._active_sums(zc) if fixed is None else self._active_sums(zc) + fixed
            means = (sums / self._block_sizes[:, None]).astype(np.float32)
            # einsum, not matmul: BLAS threads would spin against Dr.Jit's on the same cores (10× slower here).
            low = np.einsum("cub,bc->uc", self._responses, means)
            out = out + dr.block_sum(dr.gather(self._float, self._float(np.ascontiguousarray(low).ravel()),
                                               self._low_src) * self._low_w, 4)
        return out

    def direct(self, flat: Any) -> Any:
        """The direct light ``D z`` on the rows (a flat Dr.Jit array, rows × 3, not yet evaluated) for a compact
        ``flat`` Dr.Jit input (active texels × 3)."""
        dr = self._dr
        out = dr.block_sum(dr.gather(self._float, flat, self._src) * self._w, self._k)
        if self._spread is None:
            return out
        return dr.gather(self._float, out, *self._spread)

    def adjoint_pending(self, r: np.ndarray) -> tuple[Any, Any]:
        """The two gathers of ``Tᵀ r`` (direct on the active texels; the upsampling's adjoint, None without an
        indirect part) as Dr.Jit arrays not yet evaluated (:func:`adjoint_together`)."""
        dr = self._dr
        values = self._float(np.ascontiguousarray(r, dtype=np.float32).ravel())
        cols = dr.block_sum(dr.gather(self._float, values, self._col_src) * self._col_w, self._kc)
        if not self._nb:
            return cols, None
        return cols, dr.block_sum(dr.gather(self._float, values, self._up_src) * self._up_w, self._kl)

    def _parts_of(self, cols: Any, low: Any) -> tuple[np.ndarray, np.ndarray | None]:
        """:meth:`adjoint_pending`'s two arrays (evaluated or not) as ``Tᵀ r`` in two parts: (A, 3) direct light on
        the active texels, and (blocks, 3) what each texel of a block does through interreflection (None without).
        Both gathers run as one launch where they are still pending."""
        if low is None:
            return np.asarray(cols).reshape(-1, 3), None
        self._dr.eval(cols, low)
        per_block = np.einsum("cub,uc->bc", self._responses, np.asarray(low).reshape(-1, 3))
        return np.asarray(cols).reshape(-1, 3), per_block / self._block_sizes[:, None]

    def adjoint_finish(self, cols: Any, low: Any, out: np.ndarray | None = None) -> np.ndarray:
        """(A, 3) ``Tᵀ r`` from :meth:`adjoint_pending`'s two arrays (evaluated or not), written into ``out``
        where given (an (A, 3) float32 array: a joint solve's part of its concatenated vector)."""
        direct, per_block = self._parts_of(cols, low)
        if out is None:
            out = direct
        else:
            out[...] = direct
        if per_block is not None:
            out += np.repeat(per_block.astype(np.float32)[self._runs], self._run_counts, axis=0)
        return out

    def _adjoint_parts(self, r: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """``Tᵀ r`` in two parts (:meth:`_parts_of`) for an (R, 3) ``r``."""
        return self._parts_of(*self.adjoint_pending(r))

    def adjoint_compact(self, r: np.ndarray) -> np.ndarray:
        """(A, 3) ``Tᵀ r`` on the active texels, for an (R, 3) ``r``."""
        return self.adjoint_finish(*self.adjoint_pending(r))

    def apply(self, z: np.ndarray) -> np.ndarray:
        """(R, 3) ``T z`` for an input-size ``z``."""
        return self.apply_compact(self.compact(z), self.fixed_sums(z))

    def adjoint(self, r: np.ndarray) -> np.ndarray:
        """``Tᵀ r`` at the input size (every texel; the inactive ones through interreflection alone)."""
        iw, ih = self.op.input_size
        cols, per_block = self._adjoint_parts(r)
        out = np.zeros((iw * ih, 3), np.float32)
        if per_block is not None:
            out += self.op._spread(per_block).reshape(-1, 3)
        out[self.texels] += cols
        return out.reshape(ih, iw, 3)


def gaussian_taps(sigma: float) -> np.ndarray:
    """The lens blur's one-dimensional Gaussian of ``sigma`` texels (±4σ, as OpenCV sizes it): the blur is
    separable, ``B = B_y B_x``, and the real-time solve filters with the same taps."""
    return cv2.getGaussianKernel(int(round(8.0 * float(sigma) + 1.0)) | 1, float(sigma), cv2.CV_32F).ravel()


def lens_blur(z: np.ndarray, sigma: float) -> np.ndarray:
    """An input-size image after a Gaussian lens blur of ``sigma`` texels, with no light beyond its edges."""
    g = gaussian_taps(sigma)
    return cv2.sepFilter2D(np.asarray(z, np.float32), -1, g, g, borderType=cv2.BORDER_CONSTANT)


def apply_together(views: Sequence[Any], zcs: Sequence[np.ndarray], fixed: Sequence[Any]) -> list[np.ndarray]:
    """Each view's ``apply_compact(zc, fixed)``, those of the :class:`TransportRows` among them evaluated in one
    Dr.Jit launch: several projectors' operators on the same camera rows then make one kernel instead of one each
    (the same values; on 2 cores a launch's fixed cost and its threads' start were a share of the joint solve)."""
    pending = [v.apply_pending(z, f) if isinstance(v, TransportRows) else None for v, z, f in zip(views, zcs, fixed)]
    ready = [p for p in pending if p is not None]
    if len(ready) > 1:
        next(v for v in views if isinstance(v, TransportRows))._dr.eval(*ready)
    return [np.asarray(p).reshape(-1, 3) if p is not None else v.apply_compact(z, f)
            for v, z, f, p in zip(views, zcs, fixed, pending)]


def adjoint_together(views: Sequence[Any], rs: Sequence[np.ndarray]) -> np.ndarray:
    """The views' ``adjoint_compact(r)`` concatenated, the gathers of the :class:`TransportRows` among them
    evaluated in one Dr.Jit launch (as :func:`apply_together`) and each written into its part of the result."""
    pending = [v.adjoint_pending(r) if isinstance(v, TransportRows) else None for v, r in zip(views, rs)]
    ready = [a for p in pending if p is not None for a in p if a is not None]
    if len(ready) > 1:
        next(v for v in views if isinstance(v, TransportRows))._dr.eval(*ready)
    bounds = np.cumsum([0] + [len(v.texels) for v in views])
    out = np.empty((int(bounds[-1]), 3), np.float32)
    for v, r, p, a, b in zip(views, rs, pending, bounds[:-1], bounds[1:]):
        if p is not None:
            v.adjoint_finish(*p, out=out[a:b])
        else:
            out[a:b] = v.adjoint_compact(r)
    return out


class BlurredRows:
    """``T B``: a :class:`TransportRows` after a Gaussian blur of the input (``sigma`` texels: a projector lens out
    of focus, as the diagnosis fitted it), with the same interface for stage C's solver.

    Why inside the solve rather than pre-sharpening its answer: a camera pixel averages several texels, so the
    camera sees only the blur's effect at its own resolution; a solve through ``T B`` sharpens for that, within
    [0, 1], where matching the wanted input texel by texel (what pre-sharpening does) spends the input's range on
    detail no camera pixel resolves. The unknowns are the texels whose blurred light reaches a texel the rows see
    directly (the view's active texels grown by the blur's reach, :func:`gaussian_taps`); the others are held at
    the start's values, as :class:`TransportRows` holds its inactive texels. Those reach the rows through
    interreflection alone, as their block's mean: solved too, they lit the surround outside the display area in
    bright blocks, which bounce only a little light into it (`--effects auto` on the lab: 93–108 % of the
    picture's level outside the area). The blur has zero borders, no light beyond the input's edge, which makes it
    symmetric: it is its own adjoint."""

    def __init__(self, view: TransportRows, sigma: float) -> None:
        self.view, self.sigma = view, float(sigma)
        self.op, self.rows = view.op, view.rows
        iw, ih = view.op.input_size
        self._shape = (ih, iw, 3)
        direct = np.zeros((ih, iw), np.uint8)
        direct.reshape(-1)[view.texels] = 1
        reach = len(gaussian_taps(self.sigma)) // 2
        grown = cv2.dilate(direct, np.ones((2 * reach + 1, 2 * reach + 1), np.uint8))
        #: the unknowns (flat input indices): the texels whose blurred light reaches the rows directly
        self.texels = np.flatnonzero(grown.reshape(-1))
        self._row_ones: np.ndarray | None = None

    def blur(self, z: np.ndarray) -> np.ndarray:
        """``B z`` for an input-size ``z``."""
        return lens_blur(np.asarray(z, np.float32).reshape(self._shape), self.sigma)

    def compact(self, z: np.ndarray) -> np.ndarray:
        """(A, 3) values of the unknown texels of an input-size ``z``."""
        return np.asarray(z, np.float32).reshape(-1, 3)[self.texels]

    def expand(self, zc: np.ndarray, z: np.ndarray) -> np.ndarray:
        """``z`` (input size) with its unknown texels replaced by ``zc``."""
        out = np.array(z, np.float32).reshape(-1, 3)
        out[self.texels] = zc
        return out.reshape(np.shape(z))

    def fixed_sums(self, z: np.ndarray) -> np.ndarray:
        """The held texels: ``z`` (input size) with its unknowns zeroed (what :meth:`apply_compact` adds)."""
        out = np.array(z, np.float32).reshape(-1, 3)
        out[self.texels] = 0.0
        return out.reshape(self._shape)

    @property
    def row_ones(self) -> np.ndarray:
        if self._row_ones is None:
            self._row_ones = self.apply(np.ones(self._shape, np.float32))
        return self._row_ones

    def apply(self, z: np.ndarray) -> np.ndarray:
        """(R, 3) ``T B z`` for an input-size ``z``."""
        return self.view.apply(self.blur(z))

    def apply_compact(self, zc: np.ndarray, fixed: np.ndarray | None = None) -> np.ndarray:
        """(R, 3) ``T B z`` where ``z`` holds ``zc`` on the unknowns and ``fixed`` (:meth:`fixed_sums`; None:
        black) elsewhere."""
        held = np.zeros(self._shape, np.float32) if fixed is None else fixed
        return self.apply(self.expand(zc, held))

    def adjoint_compact(self, r: np.ndarray) -> np.ndarray:
        """(A, 3) ``Bᵀ Tᵀ r`` = ``B Tᵀ r`` on the unknowns."""
        return self.blur(self.view.adjoint(r)).reshape(-1, 3)[self.texels]


# -- building -------------------------------------------------------------------------------------------------

def camera_to_input(calibration: Any, camera_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Where each camera pixel looks in the projector input (continuous texel coordinates, x and y), and whether
    that surface point is lit by the projector at all (ray cast both ways through the calibrated model)."""
    return camera_to_input_of(calibration.rig, calibration.surface, camera_size)


def camera_to_input_of(rig: Any, surface: Any, camera_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """:func:`camera_to_input` for a rig and surface not yet gathered into a calibration (stage B uses it)."""
    cam = rig.camera.intrinsics.scaled(*camera_size)
    cw, ch = camera_size
    ys, xs = np.mgrid[0:ch, 0:cw] + 0.5
    rays = cam.rays(np.stack([xs.ravel(), ys.ravel()], axis=1))
    t = first_hits(surface, np.zeros(3), rays)
    hit = np.isfinite(t)
    points = rays * np.where(hit, t, 1.0)[:, None]
    proj = rig.projector
    pose = proj.camera_from_projector
    towards = points - pose[:3, 3]
    t_proj = first_hits(surface, pose[:3, 3], towards)
    lit = hit & np.isfinite(t_proj) & (t_proj > 1.0 - 1e-3)
    px = proj.project(points)
    x0, y0 = proj.input_offset
    u = np.stack([px[:, 0] - x0, px[:, 1] - y0], axis=1)
    iw, ih = proj.input_size
    lit &= np.isfinite(u).all(axis=1) & (u[:, 0] > -1) & (u[:, 1] > -1) & (u[:, 0] < iw + 1) & (u[:, 1] < ih + 1)
    return np.where(lit[:, None], u, np.nan).reshape(ch, cw, 2), lit.reshape(ch, cw)


def footprint_radius(u: np.ndarray) -> np.ndarray:
    """Per camera pixel, the radius in input texels of the texels that can light it: half its extent in the
    input (from the neighbours' correspondence) plus the bilinear lookup's one texel."""
    dx = np.abs(np.diff(u, axis=1, append=np.nan))
    dy = np.abs(np.diff(u, axis=0, append=np.nan))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # pixels whose neighbours all miss the surface
        stretch = np.nanmax(np.stack([dx[..., 0], dx[..., 1], dy[..., 0], dy[..., 1]], axis=-1), axis=-1)
    return 0.5 * math.sqrt(2.0) * stretch + 1.0


def lattice_nodes(flat_u: np.ndarray, ok: np.ndarray, a: int, b: int, spacing: int, input_size: tuple[int, int]
                  ) -> tuple[np.ndarray, np.ndarray]:
    """For the lattice of every ``spacing``-th texel from row ``a``, column ``b``: the node nearest to where each
    camera pixel looks (``flat_u``, (P, 2) input coordinates, texel centres at index + 0.5), as a flat texel index
    (0 where none), and whether it has one (``ok``: the pixel sees the projector; the node inside the input)."""
    iw, ih = input_size
    col = b + spacing * np.round((np.nan_to_num(flat_u[:, 0]) - 0.5 - b) / spacing)
    row = a + spacing * np.round((np.nan_to_num(flat_u[:, 1]) - 0.5 - a) / spacing)
    inside = ok & (col >= 0) & (col < iw) & (row >= 0) & (row < ih)
    return np.where(inside, row * iw + col, 0).astype(np.int32), inside


def largest_entries(index: np.ndarray, weight: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Each camera pixel's ``k`` largest entries of (P, n) ``index`` and (P, n, 3) ``weight`` (all of them, in their
    order, when there are no more than ``k``), and the share of the light the others held."""
    total = float(weight.sum())
    if index.shape[1] > k:
        keep = np.argsort(-weight.sum(axis=2), axis=1)[:, :k]
        index = np.take_along_axis(index, keep, axis=1)
        weight = np.take_along_axis(weight, keep[..., None], axis=1)
    return index, weight, 1.0 - float(weight.sum()) / max(total, 1e-12)


def build_transport(calibration: Any, *, bounces: int = 1, spp: int = DIRECT_SPP, seed: int = 0, blocks: int = 8,
                    indirect_scale: float = 0.25, indirect_spp: int = 64, variant: str | None = None,
                    progress: Progress | None = None, cancel: Cancel | None = None) -> TransportOperator:
    """Render ``T`` for a calibration (module doc). ``spp`` and ``seed`` are those of the direct renders (``T z``
    then equals the direct render of ``z`` with them)."""
    say = progress or quiet
    t0 = time.perf_counter()
    rig, surface = calibration.rig, calibration.surface
    iw, ih = rig.projector.input_size
    camera_size = rig.camera.intrinsics.size
    cw, ch = camera_size
    u, lit = camera_to_input(calibration, camera_size)
    if lit.sum() < 16:
        raise TransportError("the projector lights almost nothing the camera sees; calibrate again")
    radius = footprint_radius(u)
    r95 = float(np.nanpercentile(radius[lit], 95))
    spacing = int(min(MAX_SPACING, max(MIN_SPACING, math.ceil(2 * r95) + 1)))
    check_memory(camera_size, spacing, bounces)
    too_wide = float(np.mean(radius[lit] >= spacing / 2.0))
    model = ForwardModel(rig, surface, bounces=0, spp=spp, smoothing_eps=0.0, clamp=False, seed=seed,
                         variant=variant)
    entries_i: list[np.ndarray] = []
    entries_w: list[np.ndarray] = []
    flat_u = u.reshape(-1, 2)
    ok = lit.ravel()
    n = spacing * spacing
    for k, (a, b) in enumerate((a, b) for a in range(spacing) for b in range(spacing)):
        if cancel is not None and cancel():
            raise TransportError("precomputing the transport operator was cancelled; nothing was written")
        say(f"direct transport: lattice {k + 1}/{n} (every {spacing}th texel)", 0.8 * k / n)
        z = np.zeros((ih, iw, 3), np.float32)
        z[a::spacing, b::spacing] = 1.0
        img = model.render_input(z, seed=seed, spp=spp).reshape(-1, 3)
        node, inside = lattice_nodes(flat_u, ok, a, b, spacing, (iw, ih))
        entries_i.append(node)
        entries_w.append(np.where(inside[:, None], img, 0.0).astype(np.float32))
    index, weight, dropped = largest_entries(np.stack(entries_i, axis=1), np.stack(entries_w, axis=1), MAX_ENTRIES)
    # -- indirect blocks
    blocks_xy = (blocks, blocks) if bounces > 0 else (0, 0)
    indirect = np.zeros((0, 1, 1, 3), np.float32)
    if bounces > 0:
        low = (max(2, round(cw * indirect_scale)), max(2, round(ch * indirect_scale)))
        full = ForwardModel(rig, surface, camera_size=low, bounces=bounces, spp=indirect_spp, smoothing_eps=0.0,
                            clamp=False, seed=seed + 1, variant=variant)
        direct = ForwardModel(rig, surface, camera_size=low, bounces=0, spp=indirect_spp, smoothing_eps=0.0,
                              clamp=False, seed=seed + 1, variant=variant)
        responses = []
        for j in range(blocks * blocks):
            if cancel is not None and cancel():
                raise TransportError("precomputing the transport operator was cancelled; nothing was written")
            say(f"indirect transport: block {j + 1}/{blocks * blocks}", 0.8 + 0.2 * j / (blocks * blocks))
            by, bx = divmod(j, blocks)
            z = np.zeros((ih, iw, 3), np.float32)
            rows = (np.arange(ih) * blocks // ih) == by
            cols = (np.arange(iw) * blocks // iw) == bx
            z[np.ix_(rows, cols)] = 1.0
            # Same seed for both: the direct parts cancel sample by sample.
            responses.append(np.maximum(full.render_input(z, seed=seed + 1) - direct.render_input(z, seed=seed + 1),
                                        0.0))
        indirect = np.asarray(responses, np.float32)
    op = TransportOperator(camera_size, (iw, ih), index, weight, blocks_xy, indirect)
    op.report = {"format": FORMAT, "version": VERSION, "spacing": spacing, "direct_renders": n,
                 "direct_spp": spp, "seed": seed, "entries_per_pixel": int(index.shape[1]),
                 "pixels_lit": int(lit.sum()), "footprint_radius_p95": round(r95, 2),
                 "pixels_wider_than_spacing": round(too_wide, 5), "light_dropped": round(dropped, 6),
                 "indirect_blocks": list(blocks_xy), "indirect_size": list(indirect.shape[1:3][::-1]),
                 "indirect_spp": indirect_spp if bounces else None, "bounces": bounces,
                 "seconds": round(time.perf_counter() - t0, 2), "megabytes": round(op.nbytes / 2 ** 20, 1)}
    say("transport operator ready", 1.0)
    return op


__all__ = ["TransportError", "TransportMemoryError", "TransportOperator", "adjoint_together", "apply_together",
           "build_transport", "building_bytes",
           "camera_to_input", "camera_to_input_of", "check_memory", "free_bytes", "gaussian_taps", "largest_entries",
           "lattice_nodes"]
