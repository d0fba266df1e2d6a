"""One section of the report per step folder: what each step wrote, read back and turned into blocks of the page.

A section is a dict the page template draws: a title, the folder, and blocks
(a headline, facts, a table, a figure with its caption, a thumbnail strip, a
note). Each reader takes what the folder holds and leaves out, with a note and
an entry under *Skipped*, what is missing: a missing image never stops the
report. A manifest that lacks a key this version records raises (KeyError …),
and the report step skips the whole folder, saying it is from an older version.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..capture.format import CaptureSet
from ..capture.patterns import decode_gray_code_set
from ..errors import ProCamError
from ..imageio import read_arrays, read_image
from ..report import figures
from ..safepaths import inside
from ..steps.summary import fmt
from ..stages.intrinsics import pose_summary
from . import compensate as compensate_step
from . import layout

Block = dict[str, Any]


def _figure(uri: str, caption: str, alt: str) -> Block:
    return {"type": "figure", "uri": uri, "caption": caption, "alt": alt}


def _db(value: Any) -> str:
    return fmt(value, ".2f", " dB")


class Reader:
    """Reads the step folders the walk found into sections; ``skip(path, reason)`` records what it leaves out."""

    def __init__(self, found: list[Any], skip: Callable[[str | Path, str], None], *, thumbnails: int = 24) -> None:
        self.found = found
        self.skip = skip
        self.thumbnails = thumbnails

    # -- helpers -------------------------------------------------------------------------------------------------

    def image(self, folder: Path, name: Any, what: str, blocks: list[Block]) -> np.ndarray | None:
        """The image ``name`` (a name a manifest gave, or one the step always writes) inside ``folder``; None, a
        note and a skipped entry when it is missing or cannot be read."""
        try:
            path = inside(folder, name, what=what)
            return read_image(path)
        except ProCamError as exc:
            self.skip(folder, f"{what} is not shown: {exc}")
            blocks.append({"type": "note", "text": f"{what} is not shown: {exc}"})
            return None

    def _kind_at(self, path: Any, kind: layout.FolderKind) -> Path | None:
        """The folder of ``kind`` at ``path`` (as a manifest recorded it), else one of that kind the walk found
        beside the folders read (a tree moved since it was made)."""
        if isinstance(path, str) and path and kind.holds(path):
            return Path(path)
        named = Path(path).name if isinstance(path, str) and path else ""
        for f in self.found:
            if f.kind is kind and (not named or f.path.name == named):
                return f.path
        return None

    def captures(self, path: Any) -> CaptureSet | None:
        folder = self._kind_at(path, layout.CAPTURES)
        if folder is None:
            return None
        try:
            return CaptureSet.load(folder, verify_images=False)
        except ProCamError:
            return None

    # -- sections ------------------------------------------------------------------------------------------------

    def section(self, f: Any) -> dict[str, Any]:
        readers = {layout.DEMO.format: self.demo, layout.CALIBRATION.format: self.calibration,
                   layout.COMPENSATION.format: self.compensation, layout.EVALUATION.format: self.evaluation,
                   layout.DIAGNOSIS.format: self.diagnosis, layout.SHOW.format: self.show}
        title, blocks = readers[f.kind.format](f.path, f.doc)
        return {"title": title, "folder": str(f.path), "blocks": blocks,
                "facts": blocks[0]["items"] if f.kind is layout.DEMO else []}

    def demo(self, folder: Path, doc: dict[str, Any]) -> tuple[str, list[Block]]:
        cam, proj = doc["resolution"]["camera"], doc["resolution"]["projector"]
        items = [("demo", f"camera {cam[0]}×{cam[1]}, projector {proj[0]}×{proj[1]}, surface {doc['surface']}, "
                          f"lab effects {doc['effects']}")]
        cal = doc.get("calibration") or {}
        if "position_error_cm" in cal:
            items.append(("projector pose error", f"{fmt(cal['position_error_cm'], '.2f', ' cm')}, "
                                                  f"{fmt(cal['direction_error_deg'], '.3f', '°')} (against the lab's "
                                                  "sealed truth)"))
        m = (doc.get("compensation") or {}).get("mean")
        if m:
            items.append(("mean PSNR", f"{_db(m['uncompensated_psnr'])} uncompensated → {_db(m['psnr'])} compensated"))
        fx = doc.get("with_effects")
        if fx:
            items.append((f"with {', '.join(fx['effects'])} inverted", f"{_db(fx['mean']['psnr'])}"))
        if doc.get("seconds_total") is not None:
            items.append(("demo's running time", fmt(doc["seconds_total"], ".0f", " s")))
        return "Demo", [{"type": "facts", "items": items}]

    def calibration(self, folder: Path, doc: dict[str, Any]) -> tuple[str, list[Block]]:
        blocks: list[Block] = []
        rig = doc["rig"]
        cam = rig["camera"]["intrinsics"]
        # several projectors: the rig lists each projector, the document each one's calibration (the first's also
        # at the top, as one projector's folder has it)
        rigs = [p for p in rig.get("projectors") or [] if isinstance(p, dict)] or [rig["projector"]]
        steps = [p for p in doc.get("projectors") or [] if isinstance(p, dict)] or [doc]
        if len(steps) != len(rigs):
            steps = [doc]
            rigs = rigs[:1]
        many = len(rigs) > 1
        poses = [np.asarray(st["camera_from_projector"], np.float64) for st in steps]
        items = [("camera", f"{cam['width']}×{cam['height']} px, fx {cam['fx']:.1f}")]
        for k, (pr, pose) in enumerate(zip(rigs, poses)):
            name = f"projector {k + 1}" if many else "projector"
            pro = pr["intrinsics"]
            items += [(name, f"{pro['width']}×{pro['height']} px, fx {pro['fx']:.1f}, principal point "
                             f"({pro['cx']:.1f}, {pro['cy']:.1f})"),
                      (f"{name} position", "x {:.3f}, y {:.3f}, z {:.3f} m from the camera".format(*pose[:3, 3])),
                      (f"{name} looks along", "({:.3f}, {:.3f}, {:.3f}) (camera frame: x right, y down, z forward)"
                       .format(*pose[:3, 2]))]
            if isinstance(steps[k].get("pose_uncertainty"), dict):
                items.append((f"{name} pose uncertainty", pose_summary(steps[k]["pose_uncertainty"])))
            wr = steps[k].get("warp_report") or {}
            if wr.get("corners_before_px") and wr.get("corners_after_px"):
                before, after = wr["corners_before_px"]["median"], wr["corners_after_px"]["median"]
                items.append((f"warp (stage B){f', projector {k + 1}' if many else ''}",
                              f"checkerboard corners median {fmt(before, '.2f')} px before → {fmt(after, '.2f')} "
                              "px after"))
        seconds = doc.get("seconds") or {}
        if seconds:
            items.append(("seconds", ", ".join(f"{k} {fmt(v, '.1f')}" for k, v in seconds.items())))
        blocks.append({"type": "facts", "items": items})

        blocks.append({"type": "heading", "text": "Pose (stage A)"})
        points = None
        surface = doc.get("surface") or {}
        if surface.get("mesh"):
            try:
                mesh = inside(folder, surface["mesh"], what="the surface mesh")
                points = read_arrays(mesh, ("vertices",), error=ProCamError, remedy="calibrate again")["vertices"]
            except ProCamError as exc:
                blocks.append({"type": "note", "text": f"the surface is not shown: {exc}"})
                self.skip(folder, f"the surface mesh is not shown: {exc}")
        blocks.append(_figure(figures.pose_views([p[:3, 3] for p in poses], [p[:3, 2] for p in poses], points),
                              f"Where calibration put the projector{'s' if many else ''} relative to the camera, "
                              "with the surface's vertices (grey). Arrows: each one's optical axis.",
                              "rig seen from above and the side"))
        diag = folder / layout.DIAGNOSTICS_DIR
        for k in range(len(steps)):
            prefix, whose = (f"p{k + 1}_" if k else "", f"projector {k + 1}: " if many else "")
            if diag.is_dir():
                seen, drawn = (self.image(diag, f"{prefix}{n}", f"{whose}stage A's {w}", blocks)
                               for n, w in (("pose_mask.png", "captured lit area"),
                                            ("pose_rendered_mask.png", "rendered lit area")))
                if seen is not None and drawn is not None and seen.shape == drawn.shape:
                    a, b = seen.mean(axis=2) > 0.5, drawn.mean(axis=2) > 0.5
                    agree = np.zeros(a.shape + (3,), np.float32)
                    agree[a & b] = 0.85
                    agree[a & ~b] = (0.9, 0.62, 0.0)
                    agree[~a & b] = (0.34, 0.71, 0.91)
                    share = float((a ^ b).sum()) / max(float((a | b).sum()), 1.0)
                    blocks.append(_figure(figures.pictures([agree], [f"{whose}lit area: captured vs rendered"],
                                                           light=False, across=4.0),
                                          f"Grey: lit in the capture and in the simulation at the calibrated pose; "
                                          f"orange: lit only in the capture; blue: only in the simulation. They "
                                          f"disagree on {share:.1%} of the lit pixels.", f"{whose}pose agreement map"))
        for k, (pr, st) in enumerate(zip(rigs, steps)):
            prefix, whose = (f"p{k + 1}_" if k else "", f"projector {k + 1}: " if many else "")
            warp = st.get("warp") or {}
            if warp.get("m_shifts") is None:
                continue
            if k == 0 or not many:
                blocks.append({"type": "heading", "text": "Warp (stage B)"})
            size = tuple(int(v) for v in warp.get("size") or pr["input_size"])
            caption = (f"{whose}the warp's correction over the projector input: how far (colour) and which way "
                       "(arrows) each control point of the thin-plate spline moves the image, in input pixels. A "
                       "smooth field of under a pixel or two is usual; a large or jagged one points at a pose or a "
                       "surface that is off.")
            blocks.append(_figure(figures.warp_field(np.asarray(warp["m_shifts"], np.float64), size),
                                  caption[0].upper() + caption[1:], f"{whose}warp shift field"))
            if diag.is_dir():
                pair = [self.image(diag, f"{prefix}{n}", f"{whose}{w}", blocks) for n, w in
                        (("warp_compare_before.png", "the checkerboard before the warp"),
                         ("warp_compare_after.png", "the checkerboard after the warp"))]
                if all(p is not None for p in pair):
                    caption = (f"{whose}captured checkerboard against the simulated one, before and after the warp "
                               "(the closer the two overlays, the better).")
                    blocks.append(_figure(figures.pictures(pair, ["before the warp", "after the warp"], light=False),
                                          caption[0].upper() + caption[1:], f"{whose}warp comparison"))

        blocks.append({"type": "heading", "text": "Gray-code coverage"})
        captures = self.captures(doc.get("capture_set"))
        if captures is None:
            blocks.append({"type": "note", "text": "the capture set is not beside the calibration any more, so its "
                                                   "Gray-code coverage is not shown"})
            self.skip(folder, f"Gray-code coverage not shown: the capture set {doc.get('capture_set')} is not there")
        elif not captures.entries_of("graycode"):
            blocks.append({"type": "text", "text": "The capture set holds no Gray code."})
        else:
            views = [captures] if len(captures.projectors) == 1 else \
                [captures.for_projector(k) for k in range(len(captures.projectors))]
            for k, view in enumerate(views):
                self._coverage(view, blocks, "" if len(views) == 1 else f"projector {k + 1}: ")

        blocks.append({"type": "heading", "text": "Surface"})
        if surface.get("albedo"):
            albedo = self.image(folder, surface["albedo"], "the surface's albedo", blocks)
            if albedo is not None:
                blocks.append(_figure(figures.pictures([albedo], ["surface albedo (camera view)"], across=4.0),
                                      f"The surface's reflectance as calibration estimated it, seen from the camera "
                                      f"({surface.get('vertices', '?')} vertices, {surface.get('faces', '?')} "
                                      f"faces).", "surface albedo"))
        return "Calibration", blocks

    def _coverage(self, captures: CaptureSet, blocks: list[Block], whose: str) -> None:
        """The Gray-code coverage of one projector's captures (``whose`` names it when there are several)."""
        try:
            dec = decode_gray_code_set(captures)
            white, black = captures.image("white"), captures.image("black")
        except ProCamError as exc:
            blocks.append({"type": "note", "text": f"{whose}the Gray code cannot be decoded: {exc}"})
            self.skip(captures.path, f"{whose}Gray-code coverage not shown: {exc}")
            return
        valid = np.asarray(dec.valid, bool)
        size = captures.projector.intrinsics.size
        # lit as stage A sees it (DESIGN.md: |white − black| > 0.1)
        lit = np.abs(white - black).max(axis=2) > 0.1
        share = float((valid & lit).sum()) / max(float(lit.sum()), 1.0)
        caption = (f"{whose}where the camera decoded which projector pixel from the Gray code: {share:.0%} of the "
                   "pixels the projector lights decoded. Smooth colour ramps mean a clean decoding; speckle or holes "
                   "inside the lit area mean noise, shadow or too little contrast there.")
        blocks.append(_figure(figures.coverage(white, valid, np.asarray(dec.coords), tuple(size)),
                              caption[0].upper() + caption[1:], f"{whose}Gray-code coverage"))

    def compensation(self, folder: Path, doc: dict[str, Any]) -> tuple[str, list[Block]]:
        blocks: list[Block] = [{"type": "facts", "items": [
            ("mode", str(doc.get("mode"))), ("device", str(doc.get("device") or "none (open loop)")),
            ("effects inverted", compensate_step.effects_text(doc.get("effects")) or "none"),
            *([("radiometry", radiometry)] if (radiometry := compensate_step.radiometry_text(doc.get("radiometry")))
              else [])]}]
        rows = []
        for t in doc["targets"]:
            rows.append([t["name"], t.get("status", "?"), t.get("mode", ""), fmt(t.get("seconds"), ".1f", " s"),
                         f"{_db(t.get('psnr_simulated_start'))} → {_db(t.get('psnr_simulated'))}"])
        blocks.append({"type": "table", "head": ["target", "status", "mode", "time", "simulated PSNR start → end"],
                       "rows": rows})
        for t in doc["targets"]:
            if t.get("status") != "done":
                continue
            wanted = [(t[k], k, cap) for k, cap in (("target", "target (display area)"),
                                                     ("simulated", "simulated camera view"))]
            several = [p for p in t.get("projectors") or [] if isinstance(p, dict) and p.get("input")]
            if len(several) > 1:  # every projector's input, with its share of the light where recorded
                wanted += [(p["input"], f"projector {k + 1}'s input",
                            f"projector {k + 1} input" + (f" (share {p['share']:.0%})"
                                                          if isinstance(p.get("share"), (int, float)) else "")
                            + (f", lights {p['area_share']:.0%} of the area"
                               if isinstance(p.get("area_share"), (int, float)) else ""))
                           for k, p in enumerate(several)]
            else:
                wanted.append((t["input"], "input", "projector input"))
            pics = [(self.image(folder, file, f"{what} of {t['name']!r}", blocks), cap) for file, what, cap in wanted]
            loop = t.get("loop")
            if isinstance(loop, dict) and loop.get("per_capture"):
                blocks += self.closed_loop(folder, t["name"], loop, t.get("area"))
            shown = [(p, c) for p, c in pics if p is not None]
            if shown:
                given = "the images the projectors are" if len(several) > 1 else "the image the projector is"
                blocks.append(_figure(figures.pictures([p for p, _ in shown], [c for _, c in shown], across=2.6),
                                      f"{t['name']}: what was asked, what the simulation expects the camera to see, "
                                      f"and {given} given.", f"compensation of {t['name']}"))
        return "Compensation", blocks

    def closed_loop(self, folder: Path, name: str, loop: dict[str, Any], area: Any) -> list[Block]:
        """The measured closed loop of one target: its residual over the captures against the camera's noise, and
        the map of where it corrected the model."""
        blocks: list[Block] = []
        rms = [float(h["residual_rms"]) for h in loop["per_capture"]
               if isinstance(h, dict) and isinstance(h.get("residual_rms"), (int, float))]
        if rms:
            noise = loop.get("noise_rms")
            plot = figures.series(list(range(1, len(rms) + 1)), {"residual RMS": rms}, xlabel="capture",
                                  ylabel="RMS, linear", title=f"{name}: closed loop", from_zero=True,
                                  levels={"camera noise": noise} if isinstance(noise, (int, float)) else None)
            blocks.append(_figure(plot, f"{name}: the camera's residual (target − capture, RMS over the display area) "
                                        f"at each capture of the closed loop, beside the camera's own noise measured "
                                        f"from two captures of its first input; it stopped: {loop.get('stopped')}"
                                  + (f" — {loop['problem']}" if loop.get("problem") else "") + ".",
                                  f"closed loop of {name}"))
        correction = loop.get("correction")
        if isinstance(correction, str):
            theta = self.image(folder, correction, f"the closed loop's correction of {name!r}", blocks)
            if theta is not None:
                mag = np.asarray(theta, np.float32).mean(axis=2)
                if isinstance(area, dict) and all(isinstance(area.get(k), int) for k in ("x", "y", "width", "height")):
                    mag = mag[area["y"]:area["y"] + area["height"], area["x"]:area["x"] + area["width"]]
                scale = max(float(np.percentile(mag, 99.5)), 1e-4)
                blocks.append(_figure(figures.heat_maps([mag], ["|θ|"], scale, "light the model lacks or adds"),
                                      f"{name}: where the closed loop corrected the model (|θ|, the light per camera "
                                      "pixel the model missed or added, mean of the channels), over the display area.",
                                      f"correction map of {name}"))
        return blocks

    def evaluation(self, folder: Path, doc: dict[str, Any]) -> tuple[str, list[Block]]:
        blocks: list[Block] = []
        m, u = doc.get("mean") or {}, doc.get("mean_uncompensated") or {}
        many = int(doc.get("projector_count") or 1) > 1
        whose = "the projectors' black and white together" if many else "this projector's black and white"
        items = [("device", str(doc.get("device") or "?")),
                 ("mean PSNR", f"{_db(u.get('psnr'))} uncompensated → {_db(m.get('psnr'))} compensated"),
                 ("mean SSIM", f"{fmt(u.get('ssim'), '.3f')} → {fmt(m.get('ssim'), '.3f')}"),
                 ("ceilings (mean)", f"range {_db(doc.get('mean_range_ceiling'))} (the best any input could do with "
                                     f"{whose}), noise {_db(doc.get('mean_noise_ceiling'))} "
                                     f"(that, as a capture with the camera's noise scores it)")]
        if many:  # where the projectors' footprints overlap, and the step across the overlap's border
            items += [(f"PSNR {where} (mean)", f"{_db(u.get(key))} → {_db(m.get(key))}")
                      for where, key in (("inside the overlap", "psnr_overlap"), ("outside it", "psnr_outside"),
                                         ("along its edge", "psnr_border"))]
            items.append(("seam step (mean)", f"{fmt(u.get('seam_step'), '.4f')} → {fmt(m.get('seam_step'), '.4f')} "
                                              "(the jump across the overlap's border; lower is smoother)"))
        sp = doc.get("spill")
        if isinstance(sp, dict):  # the light outside the display area (stages/spill.py)
            items.append(("spill outside the area (mean)",
                          f"mean {fmt(sp.get('uncompensated_mean'), '.1%')} → {fmt(sp.get('mean'), '.1%')}, 99.5th "
                          f"pixel {fmt(sp.get('uncompensated_p995'), '.1%')} → {fmt(sp.get('p995'), '.1%')} of the "
                          f"picture's level (uncompensated → compensated; where the projector{'s' if many else ''} "
                          f"reach{'' if many else 'es'}, farther than {sp.get('guard_px')} px from the area)"))
        blocks.append({"type": "facts", "items": items})
        done = [t for t in doc["targets"] if t.get("status") == "done"]
        for t in doc["targets"]:
            if t.get("status") != "done":
                blocks.append({"type": "note", "text": f"target {t.get('name')!r} {t.get('status')}: "
                                                       f"{t.get('error', '')}"})
        rows = [[t["name"], _db(t["uncompensated"]["psnr"]), _db(t["psnr"]), fmt(t["uncompensated"]["ssim"], ".3f"),
                 fmt(t["ssim"], ".3f"), _db(t.get("range_ceiling")), _db(t.get("noise_ceiling")),
                 fmt(t.get("ceiling_gap_at_limit"), ".0%")] for t in done]
        blocks.append({"type": "table", "head": ["target", "PSNR uncomp.", "PSNR comp.", "SSIM uncomp.", "SSIM comp.",
                                                 "range ceiling", "noise ceiling", "gap at input limit"],
                       "rows": rows})
        if any("spill_mean" in t for t in done):
            blocks.append({"type": "table", "head": ["target", "spill mean uncomp.", "spill mean comp.",
                                                     "99.5th pixel uncomp.", "99.5th pixel comp."]
                           + (["area lit by each projector"] if many else []),
                           "rows": [[t["name"], fmt(t["uncompensated"].get("spill_mean"), ".1%"),
                                     fmt(t.get("spill_mean"), ".1%"), fmt(t["uncompensated"].get("spill_p995"), ".1%"),
                                     fmt(t.get("spill_p995"), ".1%")]
                                    + ([", ".join(fmt(v, ".0%") for v in t.get("area_shares") or [])] if many else [])
                                    for t in done]})
        if many:
            blocks.append({"type": "table", "head": ["target", "overlap share", "inside the overlap", "outside it",
                                                     "along its edge", "seam step"],
                           "rows": [[t["name"], fmt(t.get("overlap_share"), ".0%"),
                                     *(f"{_db(t['uncompensated'].get(k))} → {_db(t.get(k))}"
                                       for k in ("psnr_overlap", "psnr_outside", "psnr_border")),
                                     f"{fmt(t['uncompensated'].get('seam_step'), '.4f')} → "
                                     f"{fmt(t.get('seam_step'), '.4f')}"] for t in done]})
        if done:
            blocks.append(_figure(figures.grouped_bars(
                [t["name"] for t in done],
                {"uncompensated": [t["uncompensated"]["psnr"] for t in done],
                 "compensated": [t["psnr"] for t in done],
                 "noise ceiling": [t.get("noise_ceiling") for t in done],
                 "range ceiling": [t.get("range_ceiling") for t in done]},
                ylabel="PSNR (dB)", title="each target against its ceilings"),
                "PSNR of the capture against the target. Range ceiling: the target clipped to what the "
                f"projector{'s' if many else ''} can show at each pixel (between black and white), the best any "
                "input could do; noise ceiling: that as the camera's noise lets a capture score it. Gap at input "
                "limit: of what separates the compensated capture from the range ceiling, the share where the input "
                "is already at full or at zero, which no solver can push further.", "PSNR per target with its "
                "ceilings"))

        crops: list[tuple[np.ndarray, np.ndarray] | None] = []
        panels = []
        for t in done:
            area = t["area"]
            x, y, w, h = int(area["x"]), int(area["y"]), int(area["width"]), int(area["height"])
            files = {k: v.format(name=t["name"]) for k, v in layout.EVALUATION_FILES.items()}
            strip = self.image(folder, t["image"], f"the comparison of {t['name']!r}", blocks)
            got = self.image(folder, files["capture"], f"the compensated capture of {t['name']!r}", blocks)
            plain = self.image(folder, files["uncompensated"], f"the uncompensated capture of {t['name']!r}", blocks)
            if strip is None or got is None or plain is None:
                crops.append(None)
                continue
            target, got, plain = strip[:, :w], got[y:y + h, x:x + w], plain[y:y + h, x:x + w]
            crops.append((got, plain))
            panels.append((t, target, plain, got))
        if panels:
            err = [np.abs(g - tg).mean(axis=2) for _, tg, _, g in panels]
            scale = max(0.05, float(np.ceil(max(float(np.percentile(e, 99)) for e in err) * 20) / 20))
            blocks.append({"type": "heading", "text": "Each target"})
            for t, target, plain, got in panels:
                caps = ["target", f"uncompensated\nPSNR {t['uncompensated']['psnr']:.2f} dB, "
                                  f"SSIM {t['uncompensated']['ssim']:.3f}",
                        f"compensated\nPSNR {t['psnr']:.2f} dB, SSIM {t['ssim']:.3f}", "error of the compensated"]
                warn = " ".join(t.get("warnings") or [])
                blocks.append(_figure(figures.comparison(target, plain, got, caps, scale),
                                      f"{t['name']} ({t.get('mode', '')}): the target fitted to the display area, "
                                      f"the camera's capture of the uncompensated and of the compensated projection, "
                                      f"and where the compensated one still differs (0 … {scale:g} of full white, "
                                      f"linear; the same scale for every target). {warn}",
                                      f"target, uncompensated, compensated and error of {t['name']}"))
        flicker = doc.get("flicker")
        pairs = [(a, b) for a, b in zip(crops, crops[1:]) if a is not None and b is not None
                 and a[0].shape == b[0].shape]
        if flicker and pairs:
            show = self._kind_at(doc.get("inputs"), layout.SHOW) is not None
            x = list(range(2, len(pairs) + 2))
            blocks.append({"type": "heading", "text": "Flicker"})
            blocks.append(_figure(figures.series(
                x, {"compensated": [float(np.abs(b[0] - a[0]).mean()) for a, b in pairs],
                    "uncompensated": [float(np.abs(b[1] - a[1]).mean()) for a, b in pairs]},
                xlabel="frame" if show else "target (in the order given)",
                ylabel="mean |change| (linear)", title="change from the previous " + ("frame" if show else "target"),
                levels={"the targets' own change (mean)": float(flicker["targets"])}, from_zero=True),
                f"How much the capture changes from one {'frame' if show else 'target'} to the next inside the display "
                f"area. Compensation should not change more than the targets themselves do (dashed): excess "
                f"{fmt(flicker.get('excess'), '+.4f')} on average over {flicker.get('pairs')} pair(s).",
                "flicker over frames"))
        return "Evaluation", blocks

    def diagnosis(self, folder: Path, doc: dict[str, Any]) -> tuple[str, list[Block]]:
        blocks: list[Block] = [{"type": "headline", "text": doc["headline"]}]
        if "steps" not in doc and doc.get("projectors"):  # several projectors: one diagnosis per projector inside
            rows = [[f"projector {k + 1}", ", ".join(p.get("selected") or []) or "none"]
                    for k, p in enumerate(doc["projectors"])]
            blocks.append({"type": "table", "head": ["projector", "effects selected"], "rows": rows})
            return "Diagnosis", blocks
        res, after = doc["residual"], doc["residual_after"]
        noise = (doc.get("unexplained") or {}).get("noise_rmse")
        items = [("held-out residual", f"RMSE {fmt(res['rmse'], '.4f')} ({_db(res['psnr'])}) with the calibrated "
                                       f"simulation → {fmt(after['rmse'], '.4f')} ({_db(after['psnr'])}) with the "
                                       "selected effects"),
                 ("selected effects", ", ".join(doc["modelled"]) or "none"),
                 ("absorbed by calibration", ", ".join(doc.get("absorbed") or []) or "none"),
                 ("--effects auto inverts", ", ".join((doc.get("compensation") or {}).get("effects") or []) or "none")]
        if noise is not None:
            items.append(("the captures' noise", f"RMSE {fmt(noise, '.4f')}"))
        blocks.append({"type": "facts", "items": items})
        for w in doc.get("warnings") or []:
            blocks.append({"type": "note", "text": w})

        blocks.append({"type": "heading", "text": "Where the simulation differs"})
        scale = float(doc.get("map_scale") or 0.1)
        before = self.image(folder, "residual_abs.png", "the residual map", blocks)
        after_map = self.image(folder, "residual_after_abs.png", "the residual map with the effects", blocks)
        maps = [m for m in (before, after_map) if m is not None]
        if maps:
            titles = [t for t, m in zip(("calibrated simulation", "with the selected effects"), (before, after_map))
                      if m is not None]
            blocks.append(_figure(figures.heat_maps(maps, titles, scale, "|capture − simulation| (linear)"),
                                  "Mean absolute difference between the held-out captures and the simulation at "
                                  "each camera pixel, before and after modelling the selected effects (same scale).",
                                  "residual maps"))
        regions = doc.get("regions") or []
        if regions:
            labels = self.image(folder, "regions_label.png", "the regions' label image", blocks)
            captures = self.captures(doc.get("capture_set"))
            back = None
            if captures is not None:
                try:
                    back = captures.image("white")
                except ProCamError:
                    back = None
            if back is None:
                back = before if before is not None else np.zeros((*labels.shape[:2], 3), np.float32) \
                    if labels is not None else None
            if back is not None:
                ids = np.rint(labels[..., 0] * 255).astype(int) if labels is not None else None
                lit = ids > 0 if ids is not None else None
                outlines, names = [], []
                for k, r in enumerate(regions):
                    whole = "whole lit area" in (r.get("tags") or [])
                    mask = lit if whole else (ids == k + 1 if ids is not None else None)
                    if mask is not None and mask.shape != back.shape[:2]:
                        mask = None
                    outlines.append(mask)
                    names.append(figures.wrap(f"{k + 1}. {r.get('cause', '?')}: {r['share']:.0%} of the error — "
                                              f"{r['description']}", 52))
                blocks.append(_figure(figures.regions(back, outlines, [r["bbox"] for r in regions], names),
                                      "The places that hold most of the remaining error, each with the effect that "
                                      "explains it and its share of the held-out error. Regions over the whole lit "
                                      "area share its outline.", "regions of the remaining error"))

        steps = doc.get("steps") or []
        if steps and steps[0].get("ranking"):
            ranking = steps[0]["ranking"]
            blocks.append({"type": "heading", "text": "Which effects explain it"})
            blocks.append(_figure(figures.ranked_bars([n for n, _ in ranking], [float(v) for _, v in ranking],
                                                      xlabel="share of the held-out error removed",
                                                      title="each effect alone, fitted to the calibration's captures",
                                                      highlight=doc["modelled"]),
                                  "How much of the held-out error each candidate effect removes when it is modelled "
                                  "alone (orange: selected). A negative share makes the simulation worse.",
                                  "effects ranked"))
            added = [s for s in steps if s.get("added")]
            if added:
                labels_ = ["calibrated"] + [f"+ {s['added']}" for s in added]
                values = [float(added[0]["before"])] + [float(s["after"]) for s in added]
                blocks.append(_figure(figures.curve(labels_, values, ylabel="held-out RMSE (linear)",
                                                    title="the gap as effects are added",
                                                    reference=(float(noise), "the captures' noise")
                                                    if noise is not None else None),
                                      "The held-out error of the simulation as the greedy selection adds each effect "
                                      "in turn (structured part, pattern edges excluded); it cannot go much below "
                                      "the captures' own noise.", "gap curve"))
        return "Diagnosis", blocks

    def show(self, folder: Path, doc: dict[str, Any]) -> tuple[str, list[Block]]:
        frames = sorted((e for e in (doc["frames"] or {}).values() if isinstance(e, dict)),
                        key=lambda e: int(e["number"]))
        done = [e for e in frames if e.get("status") == "done"]
        psnr = [float(e["psnr_model"]) for e in done if e.get("psnr_model") is not None]
        items = [("frames", f"{len(done)} of {len(frames)} finished" + ("" if doc.get("complete") else
                                                                        " (the show is not complete)")),
                 ("mode", str(doc.get("mode"))), ("projectors", str(doc.get("projector_count", 1))),
                 ("model PSNR", f"{fmt(np.mean(psnr) if psnr else None, '.2f', ' dB')} mean, "
                                f"{fmt(min(psnr) if psnr else None, '.2f', ' dB')} worst")]
        blocks: list[Block] = [{"type": "facts", "items": items}]
        for fail in doc.get("failures") or []:
            blocks.append({"type": "note", "text": f"frame {fail.get('number', '?')}: {fail.get('error', fail)}"})
        if not done:
            return "Show", blocks
        count = int(doc.get("projector_count") or 1)
        pick = sorted({round(i) for i in np.linspace(0, len(done) - 1, min(self.thumbnails, len(done)))})
        for k in range(count):  # one strip per projector, the same frames
            thumbs = []
            for i in pick:
                e = done[i]
                own = e.get("projectors") or []
                file = own[k].get("file") if count > 1 and k < len(own) and isinstance(own[k], dict) else e["file"]
                img = self.image(folder, file, f"frame {e['number']}" + (f" of projector {k + 1}" if count > 1
                                                                        else ""), blocks) if file else None
                if img is not None:
                    thumbs.append({"uri": figures.image_uri(img, width=160),
                                   "caption": f"frame {e['number']} · {fmt(e.get('psnr_model'), '.1f', ' dB')}"})
            if thumbs:
                whose = f"projector {k + 1}'s input" if count > 1 else "the projector's input"
                blocks.append({"type": "strip", "thumbs": thumbs,
                               "caption": f"{len(thumbs)} of {len(done)} finished frames ({whose}, evenly spaced), "
                                          "with the model's PSNR of each"})
        numbers = [int(e["number"]) for e in done]
        blocks.append(_figure(figures.series(
            numbers, {"solved": [float(e.get("psnr_model") or np.nan) for e in done],
                      "start of the solve": [float(e.get("psnr_model_start") or np.nan) for e in done]},
            xlabel="frame", ylabel="PSNR (dB)", title="model PSNR of each frame"),
            "How close the simulated projection of each frame comes to its target (PSNR, simulation; the "
            "evaluation measures the real one), at the start of its solve (warm or cold) and at its end.",
            "per-frame PSNR"))
        blocks.append(_figure(figures.series(numbers, {"solve": [float(e.get("seconds") or np.nan) for e in done]},
                                             xlabel="frame", ylabel="seconds", title="solve time of each frame",
                                             from_zero=True),
                              "Seconds stage C took for each frame (reading and writing excluded).",
                              "per-frame solve time"))
        return "Show", blocks
