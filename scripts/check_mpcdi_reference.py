#!/usr/bin/env python3
"""ProCam's MPCDI files read by the reference C++ MPCDI library: every value it reads against what ProCam wrote.

Usage: ``PYTHONPATH=DIR .venv/bin/python scripts/check_mpcdi_reference.py --reader BUILD/read_mpcdi [--work DIR]``
(``scripts/check_mpcdi_reference.sh`` builds the reader and runs this; ``DIR`` holds a link ``procam`` to the
repository).

The files: calibrations of the lab's true rig (the curve, side by side, 30 % overlap, camera 96×72, projectors
120×90, as ``tests/test_mpcdi.py`` makes them; no renders) exported with ``procam export-mpcdi`` — one projector and
two, profiles ``2d`` (content 160×90) and ``sl`` — and one file written straight by ProCam's writer
(:func:`procam.addon.mpcdi.format.write_archive`) with values the exports cannot have without captures: a beta map
that is not zero, and an RGB alpha and beta (channel order). The reader (``scripts/mpcdi_reference/read_mpcdi.cpp``,
linked against the library) prints what the library read: the profile, level and date, per buffer its resolution,
per region its box, resolution, frustum and coordinate frame, the warp's file, unit, interpolation and origin, its
xSamples × ySamples and every sample, the alpha and beta maps' size, components and every value, and the distortion
map's samples. Each is compared with the archive as ProCam reads it back (:func:`read_mpcdi`): names and sizes
exactly, numbers exactly as the library's types hold them (the box as float32, the frustum and frame as double,
the warps bit for bit with NaN where ProCam's is NaN, the library's (x, y) against ProCam's ``[y, x]``, row 0 the top
of the raster), the maps as the 8-bit levels ProCam wrote. It prints each comparison, five samples of each grid and
map (the corners and the middle, and one inside a ramp) and the count of all that differ; exits 1 on any mismatch
or a file the library cannot read. It also says, without counting it, whether the library's optional
``ValidateProfile`` (``DoProfileValidation``, off by default and in nDisplay) accepts the file: it refuses every
level-2 file (its beta-map check, ``m_Level == 2 || m_Level == 3 && …``, lacks brackets) and an ``sl`` file of more
than one buffer (its v1.0 reading; v2.0 gives each ``sl`` region its own buffer).
"""

from __future__ import annotations

import argparse
import dataclasses
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from procam.addon.cli.app import main as procam
from procam.addon.lab.truth import make_truth
from procam.addon.mpcdi.format import Mpcdi, Region, levels, read_mpcdi, write_archive
from procam.addon.stages.calibrate import Calibration
from procam.addon.steps import calibrate as calibrate_step

CAMERA, PROJECTOR, CONTENT = (96, 72), (120, 90), "160x90"
#: the exports read: (name, projectors, profile); projectors 0: the writer's own file (:func:`synthetic`)
CASES = (("one_2d", 1, "2d"), ("two_2d", 2, "2d"), ("one_sl", 1, "sl"), ("two_sl", 2, "sl"),
         ("writer_2d", 0, "2d"))


def calibration(folder: Path, projectors: int) -> Path:
    """A calibration folder of the lab's true rig (tests/test_mpcdi.py's ``_calibration``)."""
    truth = make_truth("curve", camera_size=CAMERA, projector_size=PROJECTOR, projectors=projectors,
                       layout="side-by-side", overlap=0.3)
    cal = Calibration(truth.rig, truth.surface, None, "", other_warps=(None,) * (projectors - 1))
    folder.mkdir(parents=True)
    calibrate_step.write(folder, cal, {})
    return folder


def synthetic(path: Path) -> None:
    """Two regions of a 2d buffer with every kind of value: warps with unknown (NaN) samples, a grey alpha ramp and
    a beta that is not zero, and on the second region an RGB alpha and beta (each channel its own ramp)."""
    rng = np.random.default_rng(54)
    regions = []
    for k, (w, h, cols, rows, rgb) in enumerate(((64, 48, 17, 13, False), (40, 30, 11, 8, True))):
        warp = rng.uniform(-0.1, 1.1, (rows, cols, 3)).astype(np.float32)
        warp[0, :2, :2] = np.nan
        warp[0, :2, 2] = 1.0
        ramp = np.tile(np.linspace(0, 1, w, dtype=np.float32), (h, 1))
        beta = rng.uniform(0, 0.1, (h, w)).astype(np.float32)
        if rgb:
            ramp = np.stack([ramp, ramp[:, ::-1], np.full_like(ramp, 0.5)], axis=2)
            beta = np.stack([beta, beta * 0.5, beta[::-1]], axis=2)
        regions.append(Region(f"region_{k + 1}", 0.1 + 0.4 * k, 0.05 * k, 0.5, 0.9, (w, h), warp, ramp, beta,
                              interpolation=("linear", "smooth")[k]))
    m = Mpcdi("2d", {"display": (320, 180)}, regions)
    with open(path, "wb") as fh:
        write_archive(m, fh)


def parse(text: str) -> dict[str, list[str]]:
    """The reader's output: one ``key value…`` per line."""
    out: dict[str, list[str]] = {}
    for line in text.splitlines():
        key, _, rest = line.partition(" ")
        out[key] = rest.split(" ") if rest else []
    return out


@dataclasses.dataclass
class Check:
    """The comparisons of one file."""

    name: str
    failures: int = 0
    checks: int = 0

    def same(self, what: str, read: Any, wrote: Any, ok: bool) -> None:
        self.checks += 1
        self.failures += not ok
        print(f"  {'ok  ' if ok else 'DIFF'} {what}: reference read {read}, ProCam wrote {wrote}")


def _equal_each(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a, b = np.asarray(a, np.float32), np.asarray(b, np.float32)
    return (a == b) | (np.isnan(a) & np.isnan(b))


def _fmt(v: np.ndarray) -> list[float]:
    return [float(f"{x:.7g}") for x in np.asarray(v, np.float64).ravel()]


def _points(w: int, h: int) -> list[tuple[int, int]]:
    """Samples printed: the corners and the middle, (x, y) with y = 0 the top row."""
    return [(0, 0), (w - 1, 0), (0, h - 1), (w - 1, h - 1), (w // 2, h // 2)]


def _inside_ramp(levels: np.ndarray) -> tuple[int, int]:
    """A pixel whose value is neither the map's least nor its largest (a ramp's), else the middle."""
    v = levels.max(axis=2)
    inner = np.argwhere((v > v.min()) & (v < v.max()))
    if len(inner) == 0:
        return v.shape[1] // 2, v.shape[0] // 2
    y, x = inner[len(inner) // 2]
    return int(x), int(y)


def _grid(c: Check, read: dict[str, list[str]], key: str, what: str, want: np.ndarray) -> None:
    """A PFM grid (warp or distortion map) as the library indexes it against ProCam's ``[y, x]``, bit for bit."""
    rows, cols = want.shape[:2]
    xs, ys = int(read[f"{key}.xSamples"][0]), int(read[f"{key}.ySamples"][0])
    c.same(f"{what} xSamples × ySamples", f"{xs}×{ys}", f"{cols}×{rows}", (xs, ys) == (cols, rows))
    if (xs, ys) != (cols, rows):
        return
    got = np.array([[float(v) for v in read[f"{key}.row[{y}]"]] for y in range(ys)], np.float32).reshape(ys, xs, 3)
    for x, y in _points(cols, rows):
        c.same(f"{what}[{x},{y}]", _fmt(got[y, x]), _fmt(want[y, x]), bool(_equal_each(got[y, x], want[y, x]).all()))
    differ = int((~_equal_each(got, want)).sum())
    known = int(np.isfinite(want).sum())
    c.same(f"{what}, all {got.size} values ({known} finite)", f"{differ} differ", "0 differ", differ == 0)


def _map(c: Check, read: dict[str, list[str]], key: str, what: str, img: np.ndarray | None) -> None:
    """A blend map: its size and components, and every value as the 8-bit level ProCam wrote."""
    if img is None:
        c.same(what, "a map" if f"{key}.size" in read else "none", "none", f"{key}.size" not in read)
        return
    h, w = img.shape[:2]
    comps = 3 if img.ndim == 3 else 1
    size = [int(v) for v in read.get(f"{key}.size", ["0", "0", "0"])]
    c.same(f"{what} width height components", size, [w, h, comps], size == [w, h, comps])
    if size != [w, h, comps]:
        return
    want = np.round(np.clip(img, 0, 1) * 255).astype(int).reshape(h, w, comps)
    got = np.array([[int(v) for v in read[f"{key}.row[{y}]"]] for y in range(h)]).reshape(h, w, comps)
    for x, y in _points(w, h) + [_inside_ramp(want)]:
        c.same(f"{what}[{x},{y}]", got[y, x].tolist(), want[y, x].tolist(), bool(np.array_equal(got[y, x],
                                                                                                 want[y, x])))
    differ = int((got != want).sum())
    c.same(f"{what}, all {want.size} values ({len(np.unique(want))} levels)", f"{differ} differ", "0 differ",
           differ == 0)


def compare(m: Mpcdi, read: dict[str, list[str]], c: Check) -> None:
    """What the reference library read (``read``) against the archive as ProCam reads it (``m``)."""
    level = levels(m)[2]
    for what, got, want in (("profile", read["profile"][0], m.profile), ("level (v1.0)", int(read["level"][0]), level),
                            ("date", " ".join(read["date"]), m.date)):
        c.same(what, got, want, got == want)
    ids = sorted(k[len("buffer."):-len(".resolution")] for k in read if k.startswith("buffer."))
    c.same("buffers", ids, sorted(m.buffers), ids == sorted(m.buffers))
    for bid, (bw, bh) in m.buffers.items():
        got_b = [int(v) for v in read.get(f"buffer.{bid}.resolution", ["-1", "-1"])]
        want_b = [bw, bh] if bw > 0 else [-1, -1]
        c.same(f"buffer {bid} resolution", got_b, want_b, got_b == want_b)
    rids = sorted(k[len("region."):-len(".buffer")] for k in read if k.startswith("region.") and k.endswith(".buffer"))
    c.same("regions", rids, sorted(r.id for r in m.regions), rids == sorted(r.id for r in m.regions))
    for r in m.regions:
        p = f"region.{r.id}"
        if f"{p}.buffer" not in read:
            continue
        c.same(f"{r.id} buffer", read[f"{p}.buffer"][0], r.buffer, read[f"{p}.buffer"][0] == r.buffer)
        box = np.array([float(v) for v in read[f"{p}.box"]], np.float32)  # the library's floats
        want_box = np.array([r.x, r.y, r.xsize, r.ysize], np.float32)
        c.same(f"{r.id} x y xsize ysize (float32)", _fmt(box), _fmt(want_box), bool(np.array_equal(box, want_box)))
        res = [int(v) for v in read[f"{p}.resolution"]]
        c.same(f"{r.id} resolution", res, list(r.resolution), res == list(r.resolution))
        for key, val in (("frustum", r.frustum), ("coordinateFrame", r.frame)):
            got_v = None if f"{p}.{key}" not in read else [float(v) for v in read[f"{p}.{key}"]]
            want_v = None if val is None else [float(v) for v in val.values()]
            c.same(f"{r.id} {key} (double)", got_v, want_v, got_v == want_v)
        for what, want in (("path", f"GeometryWarpFile-{r.id}.pfm"), ("geometricUnit", m.geometric_unit),
                           ("interpolation", r.interpolation), ("originOf3DData", m.origin)):
            got = read.get(f"{p}.warp.{what}", ["?"])[0]
            c.same(f"{r.id} warp {what}", got, want, got == want)
        _grid(c, read, f"{p}.warp", f"{r.id} warp", r.warp)
        _map(c, read, f"{p}.alpha", f"{r.id} alpha", r.alpha)
        _map(c, read, f"{p}.beta", f"{r.id} beta", r.beta)
        if r.distortion is not None or f"{p}.distortion.xSamples" in read:
            if r.distortion is None or f"{p}.distortion.xSamples" not in read:
                c.same(f"{r.id} distortion map", f"{p}.distortion.xSamples" in read, r.distortion is not None, False)
            else:
                _grid(c, read, f"{p}.distortion", f"{r.id} distortion", r.distortion)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--reader", required=True, type=Path, help="the reader program built against the library")
    ap.add_argument("--work", type=Path, default=None, help="folder for the calibrations and files (default: temp)")
    args = ap.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="mpcdi_reference_"))
    work.mkdir(parents=True, exist_ok=True)
    cals: dict[int, Path] = {}
    total = failed = 0
    for name, projectors, profile in CASES:
        out = work / f"{name}.mpcdi"
        if projectors == 0:
            print(f"$ (ProCam's writer) write_archive → {out}")
            synthetic(out)
        else:
            if projectors not in cals:
                cals[projectors] = calibration(work / f"cal_{projectors}", projectors)
            export = ["export-mpcdi", str(cals[projectors]), "--out", str(out), "--profile", profile,
                      "--content-size", CONTENT, "--force"]
            print(f"$ procam {' '.join(export)}", flush=True)
            if procam(export) != 0:
                print(f"{name}: procam export-mpcdi failed")
                return 1
        run = subprocess.run([str(args.reader), str(out)], capture_output=True, text=True, check=False)
        (work / f"{name}.read.txt").write_text(run.stdout + run.stderr)
        c = Check(name)
        what = "ProCam's writer, two regions" if projectors == 0 else f"{projectors} projector(s)"
        print(f"{name}: {what}, profile {profile}; the reference reader exited {run.returncode}")
        if run.returncode != 0:
            c.same("the file", (run.stdout + run.stderr).strip()[:300], "a file it reads", False)
        else:
            compare(read_mpcdi(out), parse(run.stdout), c)
        # Informational: the library's optional Profile::ValidateProfile (off by default, and in nDisplay).
        val = subprocess.run([str(args.reader), str(out), "--validate"], capture_output=True, text=True, check=False)
        said = "passes" if val.returncode == 0 else "refuses it: " + " ".join(val.stdout.split("\n")[0].split()[2:])
        print(f"  (not compared) the library's optional ValidateProfile {said}")
        print(f"{name}: {c.checks - c.failures}/{c.checks} comparisons match\n", flush=True)
        total += c.checks
        failed += c.failures
    print(f"all {len(CASES)} files: {total - failed}/{total} comparisons match"
          f"{' — every value the reference library read is what ProCam wrote' if not failed else ''}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
