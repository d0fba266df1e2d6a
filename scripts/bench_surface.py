"""Benchmark of the surface from depth: distance to the lab's true surface over the lit area, per surface and seed.

    .venv/bin/python scripts/bench_surface.py [--scale 1] [--surfaces plane,curve,vedge,hedge]
        [--seeds 0,1,2] [--variants realistic,wall,nobias,noise,holes,sensor,bias] [--out FILE.json]
    .venv/bin/python scripts/bench_surface.py --bias-probe [--surfaces ...] [--seeds ...]

For each built-in surface and seed it takes the virtual lab's depth image (a
ray cast of the true surface through the phone-LiDAR model of
``addon/lab/depth.py``; no Cycles render is needed), reconstructs the mesh
with :func:`procam.addon.surface.reconstruct.reconstruct_surface` as
calibration does, and compares it with the lab truth (evaluation only).

Lit area: the camera pixels whose true surface point lies inside the true
projector's frustum and is not shadowed from it. Per such pixel:

* ``ray``     distance between the reconstructed and the true surface along the camera ray;
* ``normal``  that displacement projected on the true surface normal: the point-to-surface distance
              to first order (exact on planar pieces); the figure the issue asks for (< 1 cm mean);
* ``signed``  mean signed depth error (+ = too far): the part no smoothing removes;
* ``shape``   mean normal distance after the one global scale about the camera that no camera or
              projector image can observe (the median ratio of true to reconstructed depth);
* ``cover``   share of lit pixels where the reconstruction has a surface (misses are not in the means).

Variants split the ``depth_noise`` effect at its ``realistic`` strength into its parts:
``sensor`` (only the 256×192 sensor and its bilinear upsampling), ``noise`` (+ noise only),
``holes`` (+ grazing holes and dropout only), ``bias`` (+ bias only), ``nobias`` (all but the
bias), ``realistic`` (all, nothing corrects the bias), and ``wall`` (all, reconstructed as
``procam calibrate`` does with the lab's capture sets: ``depth_offset`` read from the same
sensor's depth image of a flat wall at a tape-measured 1.5 m, ``lab_wall_depth`` +
``wall_depth_offset``; the truth's bias is never read).

``--bias-probe`` asks whether the calibration could find the bias itself: it
makes ideal Gray-code correspondences (each camera pixel's true surface point
seen through the lab's camera lens, projected into the true projector,
rounded to the projector pixel), lifts each camera pixel onto the
reconstructed mesh moved by −b along its ray, and fits the projector pose
for b on a grid (``cv2.solvePnPRefineLM``); a parabola through the best three
gives b̂. Conditions: ``bias`` (depth with the bias only, pinhole camera),
``noisy`` (realistic depth, pinhole camera), ``lens`` (realistic depth, the
lab's radial distortion, as the real captures have). ``Δrms`` is how much the
reprojection RMS grows 1 cm away from b̂: the evidence the images hold.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

VARIANTS = ("realistic", "wall", "nobias", "noise", "holes", "sensor", "bias")
PROBE_CONDITIONS = ("bias", "noisy", "lens")


def variant_effects(name: str) -> str:
    """The effect string of a variant, built from the ``realistic`` preset's depth parameters."""
    from procam.addon.lab.effects import parse_effects

    p = parse_effects("realistic")["depth_noise"].params
    parts = {"sensor": "realistic,depth_noise=0",
             "noise": f"realistic,depth_noise=0,depth_noise.std={p['std']}",
             "holes": f"realistic,depth_noise=0,depth_noise.holes={p['holes']},depth_noise.dropout={p['dropout']}",
             "bias": f"realistic,depth_noise=0,depth_noise.bias={p['bias']}",
             "nobias": "realistic,depth_noise.bias=0",
             "realistic": "realistic", "wall": "realistic"}
    if name not in parts:
        raise SystemExit(f"unknown variant {name!r}; choose from {', '.join(VARIANTS)}")
    return parts[name]


def lit_pixels(truth) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(camera rays with z = 1, true depth, true unit normals) of the camera pixels the true projector lights."""
    from procam.addon.render.raycast import first_hits
    from procam.addon.stages.pose import surface_view

    k = truth.rig.camera.intrinsics
    view = surface_view(truth.surface, k)
    hit = view.hit.ravel()
    pts = view.points.reshape(-1, 3)
    normals = view.normals.reshape(-1, 3)
    ys, xs = np.mgrid[0:k.height, 0:k.width] + 0.5
    rays = k.rays(np.stack([xs.ravel(), ys.ravel()], axis=1))
    proj = truth.rig.projector
    inv = np.linalg.inv(proj.camera_from_projector)
    safe = np.where(hit[:, None], pts, 0.0)
    z_proj = safe @ inv[2, :3] + inv[2, 3]
    px = proj.project(np.where((z_proj > 1e-6)[:, None], safe, proj.direction + proj.position))
    w, h = proj.intrinsics.size
    inside = hit & (z_proj > 1e-6) & (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
    # Shadowed: the projector's ray meets the surface before this point.
    t_shadow = first_hits(truth.surface, proj.position, pts[inside] - proj.position)
    lit = inside.copy()
    lit[inside] = t_shadow > 1 - 1e-4
    return rays[lit], pts[lit, 2], normals[lit]


def distances(mesh, rays: np.ndarray, depth: np.ndarray, normals: np.ndarray) -> dict[str, float]:
    """Distance statistics (cm) of ``mesh`` to the true surface points ``rays * depth``, see the module doc."""
    from procam.addon.render.raycast import first_hits

    t = first_hits(mesh, np.zeros(3), rays)
    ok = np.isfinite(t)
    r, tt, tr = rays[ok], depth[ok], t[ok]
    cos = np.abs(np.einsum("nk,nk->n", r, normals[ok])) / np.linalg.norm(r, axis=1)
    along = np.abs(tr - tt) * np.linalg.norm(r, axis=1)
    normal = along * cos
    scale = float(np.median(tt / tr))
    shape = np.abs(scale * tr - tt) * np.linalg.norm(r, axis=1) * cos
    return {"ray_mean": 100 * float(along.mean()), "ray_median": 100 * float(np.median(along)),
            "ray_p95": 100 * float(np.percentile(along, 95)),
            "normal_mean": 100 * float(normal.mean()), "normal_median": 100 * float(np.median(normal)),
            "normal_p95": 100 * float(np.percentile(normal, 95)),
            "signed_mean": 100 * float((tr - tt).mean()), "shape_mean": 100 * float(shape.mean()),
            "global_scale": scale, "cover": float(ok.mean()), "pixels": int(len(rays))}


def surface_rows(surfaces: list[str], variants: list[str], seeds: list[int], scale: float) -> list[dict]:
    from procam.addon.lab.truth import WALL_DISTANCE, lab_depth, lab_wall_depth, make_truth
    from procam.addon.native import import_pymeshlab
    from procam.addon.surface.reconstruct import reconstruct_surface, wall_depth_offset

    import_pymeshlab()  # once, outside the timings
    rows = []
    for surf in surfaces:
        for variant in variants:
            effects = variant_effects(variant)
            for seed in seeds:
                truth = make_truth(surf, effects=effects, seed=seed, scale=scale)  # evaluation only
                rays, depth_true, normals = lit_pixels(truth)
                depth, info = lab_depth(truth)
                t0 = time.perf_counter()
                offset = wall_depth_offset(lab_wall_depth(truth), WALL_DISTANCE) if variant == "wall" else 0.0
                mesh, _ = reconstruct_surface(depth, info.intrinsics, depth_offset=offset)
                seconds = time.perf_counter() - t0
                row = {"surface": surf, "variant": variant, "effects": effects, "seed": seed,
                       **distances(mesh, rays, depth_true, normals), "seconds": seconds}
                rows.append(row)
                print(f"# {surf} {variant} seed {seed}: normal mean {row['normal_mean']:.3f} cm, "
                      f"{seconds:.2f} s", file=sys.stderr, flush=True)
    return rows


def print_surface_table(rows: list[dict]) -> None:
    """One line per surface and variant: means over the seeds, with the range of the mean in brackets."""
    print("| surface | variant | seeds | mean cm (normal) | median | p95 | mean cm (ray) | p95 | signed cm | "
          "shape cm | cover | seconds |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    keys = list(dict.fromkeys((r["surface"], r["variant"]) for r in rows))
    for surf, variant in keys:
        sel = [r for r in rows if r["surface"] == surf and r["variant"] == variant]

        def avg(k: str) -> float:
            return float(np.mean([r[k] for r in sel]))  # noqa: B023 — called only within this iteration

        lo, hi = min(r["normal_mean"] for r in sel), max(r["normal_mean"] for r in sel)
        print(f"| {surf} | {variant} | {len(sel)} | {avg('normal_mean'):.2f} ({lo:.2f}–{hi:.2f}) | "
              f"{avg('normal_median'):.2f} | {avg('normal_p95'):.2f} | {avg('ray_mean'):.2f} | {avg('ray_p95'):.2f} | "
              f"{avg('signed_mean'):+.2f} | {avg('shape_mean'):.2f} | {min(r['cover'] for r in sel):.3f} | "
              f"{avg('seconds'):.2f} |")


def bias_probe(surf: str, condition: str, seed: int, scale: float, points: int = 40000) -> dict:
    """Fit the projector pose and the depth bias together on ideal Gray-code correspondences (module doc)."""
    import cv2

    from procam.addon.lab.effects import _undistort_normalised
    from procam.addon.lab.truth import lab_depth, make_truth
    from procam.addon.render.raycast import first_hits
    from procam.addon.surface.reconstruct import reconstruct_surface

    effects = variant_effects("bias") if condition == "bias" else "realistic"
    truth = make_truth(surf, effects=effects, seed=seed, scale=scale)  # evaluation only
    k, proj = truth.rig.camera.intrinsics, truth.rig.projector
    rng = np.random.default_rng(seed)
    ys, xs = np.mgrid[0:k.height, 0:k.width] + 0.5
    pix = np.stack([xs.ravel(), ys.ravel()], axis=1)
    pix = pix[rng.choice(len(pix), min(points, len(pix)), replace=False)]
    dist = truth.effects["distortion"]
    k1, k2 = (float(dist["k1"]), float(dist["k2"])) if condition == "lens" else (0.0, 0.0)
    xu, yu = _undistort_normalised((pix[:, 0] - k.cx) / k.fx, (pix[:, 1] - k.cy) / k.fy, k1, k2)
    true_rays = np.stack([xu, yu, np.ones_like(xu)], axis=1)
    t = first_hits(truth.surface, np.zeros(3), true_rays)
    pts = true_rays * np.where(np.isfinite(t), t, 1.0)[:, None]
    u = proj.project(pts)
    w, h = proj.intrinsics.size
    ok = np.isfinite(t) & (u[:, 0] >= 0) & (u[:, 0] < w) & (u[:, 1] >= 0) & (u[:, 1] < h)
    decoded = np.floor(u) + 0.5  # Gray code gives the projector pixel (its centre, corner convention)
    depth, info = lab_depth(truth)
    mesh, _ = reconstruct_surface(depth, info.intrinsics)
    ideal = k.rays(pix)  # the pipeline's camera model has no distortion
    z = first_hits(mesh, np.zeros(3), ideal)
    ok &= np.isfinite(z)
    r, z, img = ideal[ok], z[ok], decoded[ok] - 0.5  # OpenCV's pixel-centre convention
    K = proj.intrinsics.opencv_matrix()
    inv = np.linalg.inv(proj.camera_from_projector)
    rv0, _ = cv2.Rodrigues(inv[:3, :3])
    tv0 = inv[:3, 3].reshape(3, 1)

    def rms(b: float) -> float:
        obj = r * (z - b)[:, None]
        rv, tv = cv2.solvePnPRefineLM(obj, img, K, None, rv0.copy(), tv0.copy())
        pp, _ = cv2.projectPoints(obj, rv, tv, K, None)
        return float(np.sqrt(np.mean(np.sum((pp.reshape(-1, 2) - img) ** 2, axis=1))))

    grid = np.arange(-0.05, 0.0501, 0.01)
    vals = np.array([rms(b) for b in grid])
    i = int(np.clip(np.argmin(vals), 1, len(grid) - 2))
    c = np.polyfit(grid[i - 1:i + 2], vals[i - 1:i + 2] ** 2, 2)
    b_hat = float(-c[1] / (2 * c[0])) if c[0] > 0 else float(grid[np.argmin(vals)])
    at = rms(b_hat)
    rise = 0.5 * (rms(b_hat - 0.01) + rms(b_hat + 0.01)) - at
    return {"surface": surf, "condition": condition, "seed": seed,
            "bias_true_cm": 100 * float(truth.effects["depth_noise"]["bias"]), "bias_hat_cm": 100 * b_hat,
            "rms_px": at, "rms_rise_per_cm_px": rise, "k1": k1, "points": int(ok.sum())}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scale", type=float, default=1.0, help="share of the 640×480 camera (default full resolution)")
    ap.add_argument("--surfaces", default="plane,curve,vedge,hedge")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--bias-probe", action="store_true", help="instead: can Gray code + PnP find the depth bias?")
    ap.add_argument("--out", type=Path, default=None, help="also write the rows as JSON here")
    args = ap.parse_args(argv)
    surfaces = args.surfaces.split(",")
    seeds = [int(s) for s in args.seeds.split(",")]

    if args.bias_probe:
        rows = []
        print("| surface | condition | seed | true bias cm | fitted b̂ cm | rms px | Δrms px at b̂ ± 1 cm |")
        print("|---|---|---|---|---|---|---|")
        for surf in surfaces:
            for condition in PROBE_CONDITIONS:
                for seed in seeds:
                    row = bias_probe(surf, condition, seed, args.scale)
                    rows.append(row)
                    # A flat profile (the plane) holds no evidence: its parabola's vertex means nothing.
                    fitted = f"{row['bias_hat_cm']:+.2f}" if row["rms_rise_per_cm_px"] > 1e-5 else "none (flat)"
                    print(f"| {surf} | {condition} | {seed} | {row['bias_true_cm']:.2f} | {fitted} | "
                          f"{row['rms_px']:.4f} | {row['rms_rise_per_cm_px']:.5f} |", flush=True)
    else:
        rows = surface_rows(surfaces, args.variants.split(","), seeds, args.scale)
        print_surface_table(rows)
    if args.out is not None:
        args.out.write_text(json.dumps({"scale": args.scale, "bias_probe": args.bias_probe, "rows": rows},
                                       indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
