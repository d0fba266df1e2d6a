"""The real-data figures of ``procam calibrate-rig``, next to the calibration the data's author published.

    python scripts/bench_calibrate_rig.py [REALDATA_DIR]

Runs the rig calibration on ``realdata/kamino410-procam-calibration`` (4 board poses; the author's
``calibration_result.xml`` used those and a fifth) and prints per-pose and overall RMS, K, distortion, R and T
beside the published values. It also checks in which projector units the published K is: it fits our
projector corners when they are doubled, as if the author decoded with graycode_step 2, so it prints the
published projector K halved too. Writes nothing.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import cv2
import numpy as np

from procam.addon.steps.rig import pose_source, session_files
from procam.addon.stages.rig_calibration import calibrate_rig

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "realdata" / "kamino410-procam-calibration"


def _published(path: Path) -> dict[str, np.ndarray]:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    out = {k: fs.getNode(k).mat() for k in ("cam_int", "cam_dist", "proj_int", "proj_dist", "roration", "translation")}
    out["rms"] = np.array(fs.getNode("rms").real())
    fs.release()
    return out


def _k(K: np.ndarray) -> str:
    return f"fx {K[0, 0]:8.2f}  fy {K[1, 1]:8.2f}  cx {K[0, 2]:8.2f}  cy {K[1, 2]:8.2f}"


def _fit(obj: np.ndarray, pix: np.ndarray, K: np.ndarray, dist: np.ndarray) -> float:
    """RMS of the best pose of a planar board seen through fixed intrinsics (PnP)."""
    ok, r, t = cv2.solvePnP(obj, pix, K, dist)
    proj, _ = cv2.projectPoints(obj, r, t, K, dist)
    return float(np.sqrt(((proj.reshape(-1, 2) - pix) ** 2).sum(axis=1).mean()))


def main(root: Path = REAL) -> int:
    np.set_printoptions(precision=5, suppress=True, linewidth=120)
    sessions = sorted(root.glob("capture_*"))
    if not sessions:
        print(f"no capture_* folders in {root}")
        return 1
    size = (1024, 768)
    start = time.monotonic()
    sources = [pose_source(s, session_files(s, size)) for s in sessions]
    cal = calibrate_rig(sources, (9, 7), 1.0, size)
    seconds = time.monotonic() - start
    pub = _published(root / "calibration_result.xml")

    print(f"calibrate-rig on {root.name}: {len(cal.used)} poses used, {seconds:.1f} s")
    print(f"{'pose':<11}{'corners':>8}{'decoded':>8}{'share':>7}{'cam RMS':>9}{'proj RMS':>9}"
          f"{'stereo cam':>11}{'stereo proj':>12}")
    for p in cal.poses:
        if not p.used:
            print(f"{p.name:<11} skipped: {p.reason}")
            continue
        print(f"{p.name:<11}{p.corners_found:>8}{p.corners_decoded:>8}{100 * p.decoded_share:>6.0f}%"
              f"{p.camera_rms:>9.3f}{p.projector_rms:>9.3f}{p.stereo_camera_rms:>11.3f}{p.stereo_projector_rms:>12.3f}")
    print(f"RMS px: camera {cal.camera_rms:.3f}  projector {cal.projector_rms:.3f}  stereo {cal.stereo_rms:.3f} "
          f"({cal.stereo_flags})   published stereo {float(pub['rms']):.3f} (5 poses, its projector units)")
    print()
    print(f"camera K    ours      {_k(cal.camera_matrix)}   (OpenCV pixel centres)")
    print(f"            published {_k(pub['cam_int'])}")
    print(f"camera dist ours      {cal.camera_distortion}  ({cal.camera_model})")
    print(f"            published {pub['cam_dist'].ravel()}")
    ys, xs = np.mgrid[0:cal.camera_size[1], 0:cal.camera_size[0]]
    seen = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64).reshape(-1, 1, 2)
    moved = np.linalg.norm(cv2.undistortPoints(seen, cal.camera_matrix, cal.camera_distortion, P=cal.camera_matrix)
                           .reshape(-1, 2) - seen.reshape(-1, 2), axis=1)
    print(f"            takes each camera pixel {np.median(moved):.2f} px (median), up to {moved.max():.2f} px, "
          "to where a pinhole puts it (what import --rig, and a live camera after it, undo)")
    half = pub["proj_int"].copy()
    half[:2] /= 2
    print(f"proj K      ours      {_k(cal.projector_matrix)}")
    print(f"            published {_k(pub['proj_int'])}")
    print(f"            published/2 {_k(half)[0:]}  (in the 1024×768 Gray-code grid, see below)")
    print(f"proj dist   ours      {cal.projector_distortion}  ({cal.projector_model})")
    for m, c in cal.projector_model_choice.get("candidates", {}).items():
        print(f"            model {m:<5} RMS {c['rms']:.3f} px, BIC {c['bic']:.1f}")
    print(f"            published {pub['proj_dist'].ravel()}")
    h = size[1]
    print(f"proj principal point below centre: ours {(cal.projector_matrix[1, 2] - h / 2) / h:.2f} frame heights, "
          f"published/2 {(half[1, 2] - h / 2) / h:.2f}")
    print("R camera → projector   ours                               published")
    for a, b in zip(cal.rotation, pub["roration"]):
        print(f"  {a}   {b}")
    T, Tp = cal.translation, pub["translation"].ravel()
    angle = np.degrees(np.arccos(np.clip(T @ Tp / np.linalg.norm(T) / np.linalg.norm(Tp), -1, 1)))
    print(f"T ours {T} squares (|T| {np.linalg.norm(T):.3f}); published {Tp} (unit of its square size, not given)")
    print(f"  direction: ours {T / np.linalg.norm(T)}, published {Tp / np.linalg.norm(Tp)}, {angle:.1f}° apart")
    print()
    # Units of the published projector K: fit each pose's projector corners with it, as they are and doubled.
    obj = np.zeros((63, 3), np.float32)
    obj[:, :2] = np.mgrid[0:9, 0:7].T.reshape(-1, 2)
    for scale in (1.0, 2.0):
        fits = [_fit(obj[o.decoded], (o.projector_corners[o.decoded] * scale).astype(np.float32), pub["proj_int"],
                     pub["proj_dist"]) / scale for o in cal.observations]
        print(f"published projector K on our projector corners × {scale:g}: per-pose PnP RMS "
              f"{', '.join(f'{v:.2f}' for v in fits)} (grid px)")
    ours = [_fit(obj[o.decoded], o.projector_corners[o.decoded].astype(np.float32), cal.projector_matrix,
                 cal.projector_distortion) for o in cal.observations]
    print(f"our projector K on our projector corners:          per-pose PnP RMS {', '.join(f'{v:.2f}' for v in ours)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1]) if len(sys.argv) > 1 else REAL))
