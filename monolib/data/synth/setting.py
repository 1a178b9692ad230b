"""One setting, built (family, layout, mesh, trajectories), rendered frame by frame and written into its folder in
Hypersim's layout (`render_setting`: ``_detail/`` camera files and ``images/`` HDF5 files and previews)."""
from __future__ import annotations

import csv
import io as _io
import time
from pathlib import Path
from typing import Optional

import numpy as np

from monolib.data.hypersim import Camera, tonemap
from monolib.data.synth.cameras import _camera_M, make_trajectories, scene_exposures, setting_exposure
from monolib.data.synth.mesh import build_mesh
from monolib.data.synth.render import Renderer, render_frame
from monolib.data.synth.rooms import make_family, make_layout
from monolib.io import atomic_path, write_h5, write_json, write_text


H5_COMPRESSION = 1  # gzip level (Hypersim uses 9): level 1 writes a 256x192 frame in about 2/3 of level 4's time


def build_setting(s: dict, seed: int):
    fam = make_family(seed, s["family"], s["room_type"])
    lay = make_layout(fam, seed, s["index"], s["dim"])
    mesh = build_mesh(fam, lay, seed, s["index"])
    r = Renderer(mesh, lay, exact_ties=s.get("coplanar") == "exact")  # (a plan without it: embree)
    scenes = make_trajectories(lay, s["frames"], seed, s["index"], r)
    return fam, lay, mesh, scenes, r


def _write_csv(path: Path, header: list, rows: list) -> None:
    buf = _io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    w.writerows(rows)
    write_text(path, buf.getvalue())


def _write_jpg(path: Path, rgb: np.ndarray) -> None:
    import cv2

    ok, data = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, 95])
    if not ok:
        raise RuntimeError(f"{path}: JPEG encoding failed")
    with atomic_path(path) as tmp:
        tmp.write_bytes(data.tobytes())


def render_setting(s: dict, study_key: dict, width: int, height: int, seed: int, out: Path,
                   timing: Optional[dict] = None, compression: Optional[int] = None) -> dict:
    """Render setting `s` into folder `out` (created). Returns per-setting info (scenes, frames, classes)."""
    t0 = time.perf_counter()
    compression = H5_COMPRESSION if compression is None else compression
    fam, lay, mesh, scenes, r = build_setting(s, seed)
    if timing is not None:
        timing["build"] = timing.get("build", 0.0) + time.perf_counter() - t0
    mpau = float(s["meters_per_asset_unit"])
    cam = Camera(tuple(map(tuple, _camera_M(s, width, height))), mpau)
    rays = cam.rays(height, width)
    rng = np.random.default_rng([seed, 49979687, s["index"]])
    detail = out / "_detail"
    detail.mkdir(parents=True, exist_ok=True)
    _write_csv(detail / "metadata_scene.csv", ["parameter_name", "parameter_value"],
               [["meters_per_asset_unit", repr(mpau)]])
    _write_csv(detail / "metadata_cameras.csv", ["camera_name"], [[f"cam_{c:02d}"] for c in range(len(scenes))])
    classes: set = set()
    frames = []
    exposure = setting_exposure(r, scenes)
    for c, (eyes, Rs, looks) in enumerate(scenes):
        cname = f"cam_{c:02d}"
        cdir = detail / cname
        cdir.mkdir(parents=True, exist_ok=True)
        write_h5(cdir / "camera_keyframe_positions.hdf5", (eyes / mpau).astype(np.float64))
        write_h5(cdir / "camera_keyframe_orientations.hdf5", Rs.astype(np.float64))
        write_h5(cdir / "camera_keyframe_frame_indices.hdf5", np.arange(len(eyes), dtype=np.int64))
        write_h5(cdir / "camera_keyframe_look_at_positions.hdf5", (looks / mpau).astype(np.float64))
        _write_csv(cdir / "metadata_camera.csv", ["parameter_name", "parameter_value"], [["frame_time_seconds", "1.0"]])
        fdir = out / "images" / f"scene_{cname}_final_hdf5"
        gdir = out / "images" / f"scene_{cname}_geometry_hdf5"
        pdir = out / "images" / f"scene_{cname}_final_preview"
        for d in (fdir, gdir, pdir):
            d.mkdir(parents=True, exist_ok=True)
        exposures = exposure * scene_exposures(rng, len(eyes))
        for i, (eye, R) in enumerate(zip(eyes, Rs)):
            fo = render_frame(r, rays, eye, R, float(exposures[i]), timing)
            tw = time.perf_counter()
            stem = f"frame.{i:04d}"
            color16 = fo.color.astype(np.float16)
            write_h5(fdir / f"{stem}.color.hdf5", color16, compression)
            write_h5(gdir / f"{stem}.depth_meters.hdf5", fo.depth.astype(np.float16), compression)
            write_h5(gdir / f"{stem}.position.hdf5", (fo.position / mpau).astype(np.float16), compression)
            write_h5(gdir / f"{stem}.semantic.hdf5", fo.semantic, compression)
            write_h5(gdir / f"{stem}.semantic_instance.hdf5", fo.instance, compression)
            write_h5(gdir / f"{stem}.render_entity_id.hdf5", fo.entity, compression)
            _write_jpg(pdir / f"{stem}.tonemap.jpg", tonemap(color16.astype(np.float32), fo.entity != -1))
            if timing is not None:
                timing["write"] = timing.get("write", 0.0) + time.perf_counter() - tw
                timing["frames"] = timing.get("frames", 0) + 1
            classes.update(int(v) for v in np.unique(fo.semantic) if v > 0)
            frames.append((cname, i))
    info = dict(s)
    info.update({"scenes": [f"cam_{c:02d}" for c in range(len(scenes))],
                 "frames_per_scene": [len(e) for e, _, _ in scenes], "classes": sorted(classes),
                 "room_size_m": [round(lay.W, 3), round(lay.D, 3), round(lay.H, 3)],
                 "num_lights": len(lay.lights), "num_instances": len(mesh.instances)})
    write_json(detail / "monolib_synth_setting.json", {"key": study_key, "info": info, "files": rendered_files(out)})
    return info


MARKER = Path("_detail") / "monolib_synth_setting.json"


def rendered_files(folder: Path) -> dict[str, int]:
    """{path relative to the setting folder: size in bytes} of every file a render wrote (the marker aside): what
    `broken_files` checks a finished setting against."""
    folder = Path(folder)
    return {p.relative_to(folder).as_posix(): p.stat().st_size for p in sorted(folder.rglob("*"))
            if p.is_file() and p.relative_to(folder) != MARKER}


def broken_files(folder: Path, files: dict) -> list[str]:
    """The files of a finished setting's marker that are missing or have another size now (a truncated or deleted
    HDF5 file, a lost preview): an empty list when the render is whole. One stat per file."""
    folder = Path(folder)
    out = []
    for rel, size in files.items():
        try:
            if (folder / rel).stat().st_size != size:
                out.append(rel)
        except OSError:
            out.append(rel)
    return out
