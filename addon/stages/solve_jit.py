"""Stage C's transport solve stepped on the device: every SIRT step, one projector's or several's, in Dr.Jit.

Stepped in numpy around the operators' Dr.Jit gathers (``engine='numpy'``), each step takes every projector's
gathered light back to the host for the indirect part's block sums and its small matrix product, the blend rows,
the reach cap, the box and the momentum. On a GPU the round trips and numpy's single thread were all of it (two
projectors at 640×480: 1.07 s a target on an H200 against 1.02 s on 2 cores). Here every step stays on the Dr.Jit
backend the operators are on (``cuda_ad_rgb`` on a GPU, the LLVM one on a CPU, the same code, so the suite runs
what a GPU runs): each projector's state and each camera-row image are Dr.Jit arrays from a solve's first step to
its last, and a step's only trip to the host is the loss every tenth step (a mean). Four 1920×1080 projectors in a
2×2 grid: the 40 steps 47 ms on an H200; on 2 cores a whole target 2.61 → 2.20 s, one projector alone on the same
area 0.59 → 0.49 s (stages/solve_transport.py and stages/joint.py build a :class:`JitSteps`).

The indirect part of ``T_k z_k`` is each block's mean of the input times its low-resolution response, upsampled
to the rows. Its pieces as gathers summed in fixed-size blocks, as the direct part's are (stages/transport.py):
the active texels' sum per block is a gather padded to the largest block's run (the compact vector is ordered by
block), the blocks × responses product a gather of the means laid out (low pixel, channel, block), and its
adjoint one laid out (block, channel, low pixel). The operators, the blend rows and the reach are those of the
numpy steps; only where the arithmetic runs differs (float32 sums where numpy summed some in float64: the inputs
agree to about 1e-5).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ..errors import Cancelled
from .transport import TransportRows


class JitView:
    """One projector's :class:`~.transport.TransportRows`, applied and adjoined on Dr.Jit arrays (flat,
    channel-interleaved: rows × 3 in, active texels × 3 out and back). Made once per view (:func:`jit_view`):
    its index arrays are the view's, for every target on the same display area."""

    def __init__(self, view: TransportRows) -> None:
        dr, mi_float = view._dr, view._float
        self.view, self.dr, self.Float = view, dr, mi_float
        uint = view._uint
        self.nb = view._nb
        if not self.nb:
            return
        nb, c3 = self.nb, np.arange(3)
        runs, starts, counts = view._runs, view._run_starts, view._run_counts
        # The active texels' sum per block: each run padded to the longest, laid out (run, channel, slot).
        self.run_len = int(counts.max(initial=1))
        slot = np.arange(self.run_len)
        ok = slot[None, :] < counts[:, None]
        first = np.where(ok, starts[:, None] + slot[None, :], 0)
        self.sum_src = uint((first[:, None, :] * 3 + c3[None, :, None]).ravel().astype(np.uint32))
        self.sum_ok = view._bool(np.repeat(ok[:, None, :], 3, axis=1).ravel())
        # … put back among every block (zero where a block has no active texel)
        where = np.zeros(nb, np.int64)
        where[runs] = np.arange(len(runs))
        has = np.zeros(nb, bool)
        has[runs] = True
        self.block_src = uint((where[:, None] * 3 + c3[None, :]).ravel().astype(np.uint32))
        self.block_ok = view._bool(np.repeat(has, 3))
        self.inv_size = mi_float(np.repeat(1.0 / view._block_sizes, 3).astype(np.float32))
        resp = view._responses  # (channel, used low pixel, block)
        used = resp.shape[1]
        # low = Σ_b resp[c, u, b] means[b, c], laid out (u, c, b)
        self.resp_ucb = mi_float(np.ascontiguousarray(resp.transpose(1, 0, 2)).ravel())
        self.means_src = uint(np.broadcast_to(np.arange(nb)[None, None, :] * 3 + c3[None, :, None],
                                              (used, 3, nb)).ravel().astype(np.uint32))
        # its adjoint: per_block[b, c] = Σ_u resp[c, u, b] low[u, c], laid out (b, c, u)
        self.resp_bcu = mi_float(np.ascontiguousarray(resp.transpose(2, 0, 1)).ravel())
        self.low_src = uint(np.broadcast_to(np.arange(used)[None, None, :] * 3 + c3[None, :, None],
                                            (nb, 3, used)).ravel().astype(np.uint32))
        self.used = used
        # each active texel's block, for spreading the per-block adjoint over them
        block = np.repeat(runs, counts)
        self.texel_block = uint((block[:, None] * 3 + c3[None, :]).ravel().astype(np.uint32))

    def to_device(self, values: np.ndarray) -> Any:
        return self.Float(np.ascontiguousarray(values, np.float32).ravel())

    def fixed(self, sums: np.ndarray) -> Any:
        """The held block sums (:meth:`~.transport.TransportRows.fixed_sums`) on the device."""
        return self.to_device(sums) if self.nb else None

    def apply(self, z: Any, fixed: Any, gain: Any = None) -> Any:
        """``g T z`` on the rows for the compact ``z`` with the other texels' block sums ``fixed`` (``gain`` None:
        1)."""
        dr, view = self.dr, self.view
        out = view.direct(z)
        if self.nb:
            runs = dr.block_sum(dr.gather(self.Float, z, self.sum_src, self.sum_ok), self.run_len)
            sums = dr.gather(self.Float, runs, self.block_src, self.block_ok) + fixed
            means = sums * self.inv_size
            low = dr.block_sum(self.resp_ucb * dr.gather(self.Float, means, self.means_src), self.nb)
            out = out + dr.block_sum(dr.gather(self.Float, low, view._low_src) * view._low_w, 4)
        return out if gain is None else out * gain

    def adjoint(self, r: Any, gain: Any = None) -> Any:
        """``Tᵀ (g r)`` on the active texels for rows' values ``r``."""
        dr, view = self.dr, self.view
        values = r if gain is None else r * gain
        cols = dr.block_sum(dr.gather(self.Float, values, view._col_src) * view._col_w, view._kc)
        if not self.nb:
            return cols
        low = dr.block_sum(dr.gather(self.Float, values, view._up_src) * view._up_w, view._kl)
        per_block = dr.block_sum(self.resp_bcu * dr.gather(self.Float, low, self.low_src), self.used) * self.inv_size
        return cols + dr.gather(self.Float, per_block, self.texel_block)


def jit_view(view: TransportRows) -> JitView:
    """The view's :class:`JitView`, made on first use and kept with it."""
    made = view._jit
    if made is None:
        made = view._jit = JitView(view)
    return made


class JitSteps:
    """A transport solve's SIRT steps (:meth:`~.solve_transport.TransportSolve.solve`, with the blend rows of
    :class:`~.joint.JointSolve` when it has them) on Dr.Jit arrays: built once per solve from its numpy arrays,
    run for any number of steps from numpy states, answering numpy. ``views``, ``gains`` (None: 1), ``fixed`` (the
    held block sums) and ``col_weights`` (each projector's columns' weights at the rows) per projector; the rest is
    read from ``solve`` (its target, row sums, held texels and start, and a joint solve's blend)."""

    def __init__(self, solve: Any, views: Sequence[TransportRows], gains: Sequence[np.ndarray | None],
                 fixed: Sequence[np.ndarray], col_weights: Sequence[np.ndarray]) -> None:
        self.views = [jit_view(v) for v in views]
        first = self.views[0]
        dr = self.dr = first.dr
        self.Float, self.Bool = first.Float, first.view._bool
        self.put = put = first.to_device
        self.gains = [None if g is None else put(g) for g in gains]
        self.bounds = np.cumsum([0] + [len(v.texels) for v in views])
        self.fixed = [jv.fixed(f) for jv, f in zip(self.views, fixed)]
        self.target = put(solve.target)
        self.row_sums = put(solve.row_sums)
        # SIRT's column sums, each projector's Tᵀ (g w) for its columns' weights w (the blend rows' share in it)
        self.col_sums = [dr.maximum(jv.adjoint(put(w), g), 1e-3)
                         for jv, w, g in zip(self.views, col_weights, self.gains)]
        cuts = self.bounds[1:-1]
        self.held = [self.Bool(np.repeat(h, 3)) for h in np.split(solve.held, cuts)]
        self.start = [put(z) for z in np.split(solve.zc0, cuts)]
        self.weight = float(getattr(solve, "weight", 0.0))
        if self.weight:
            self.shares = [put(np.broadcast_to(s, solve.target.shape)) for s in solve.shares]
            self.scales = [put(s) for s in solve.blend_scale]
        reach = getattr(solve, "reach", None)
        self.reach = None if reach is None else put(reach)

    def steps(self, solve: Any, zc: np.ndarray, theta: np.ndarray, steps: int,
              residual: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``solve``'s :meth:`~.solve_transport.TransportSolve.solve` (the same steps, its cancel, progress and
        losses): the states go to the device once and come back after the last step. θ's update clips to the
        light (gains included), so with a gain other than 1 a solve following captures steps in numpy."""
        dr = self.dr
        prev = ys = self.split_to_device(zc)
        th, res = self.put(theta), None if residual is None else self.put(residual)
        for k in range(steps):
            if solve.cancel is not None and solve.cancel():
                raise Cancelled(f"compensation of {solve.name!r} cancelled at solver step {solve.done}")
            parts, total = self.forward(ys)
            if res is not None:
                th = dr.clip(th + 2.0 * solve.alpha * (res - th), total - 1.0, total)
            resid = self.target + th - total
            z_new = self.update(ys, parts, total, resid)
            momentum = dr.opaque(self.Float, k / (k + 3.0))  # opaque: one kernel for every step, not one each
            ys = [z + momentum * (z - p) for z, p in zip(z_new, prev)]
            prev = z_new
            solve.done += 1
            if k % 10 == 0 or k == steps - 1:
                loss = dr.mean(resid * resid)
                dr.eval(*ys, *prev, th, loss)
                solve.report_loss(float(loss[0]))
            else:
                dr.eval(*ys, *prev, th)
        return np.concatenate([self.back(z) for z in prev]), self.back(th)

    def split_to_device(self, zc: np.ndarray) -> list[Any]:
        return [self.put(zc[a:b]) for a, b in zip(self.bounds[:-1], self.bounds[1:])]

    def forward(self, zs: Sequence[Any]) -> tuple[list[Any], Any]:
        parts = [jv.apply(z, f, g) for jv, z, f, g in zip(self.views, zs, self.fixed, self.gains)]
        total = parts[0]
        for p in parts[1:]:
            total = total + p
        return parts, total

    def update(self, ys: Sequence[Any], parts: Sequence[Any], total: Any, resid: Any) -> list[Any]:
        """:meth:`~.joint.JointSolve.update`, boxed and held: each projector's next input before momentum."""
        dr = self.dr
        if not self.weight:
            u = resid / self.row_sums
            qs = [u] * len(ys)
        else:
            lam = self.weight
            u = (resid if self.reach is None else dr.minimum(resid, self.reach - total)) / self.row_sums
            q = [(b * total - p) * s for p, b, s in zip(parts, self.shares, self.scales)]
            mixed = self.shares[0] * q[0]
            for b, qk in zip(self.shares[1:], q[1:]):
                mixed = mixed + b * qk
            qs = [lam * (qj - mixed) + u for qj in q]
        out = []
        for jv, g, y, q, cs, held, z0 in zip(self.views, self.gains, ys, qs, self.col_sums, self.held, self.start):
            z = dr.clip(y + jv.adjoint(q, g) / cs, 0.0, 1.0)
            out.append(dr.select(held, z0, z))
        return out

    @staticmethod
    def back(values: Any) -> np.ndarray:
        return np.asarray(values, np.float32).reshape(-1, 3)


__all__ = ["JitSteps", "JitView", "jit_view"]
