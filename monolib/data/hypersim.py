"""Reading the Hypersim layout (ml-hypersim's documented file format): settings, scenes, frames, cameras, tonemap.

One reader serves a real Hypersim download and the mini-Hypersim rendered by `monolib.data.synth`, which writes the
same layout. Words: a *setting* is a folder ``ai_VVV_NNN``, a *scene* is one of its cameras ``cam_XX``, a *frame*
is ``frame.IIII`` of a scene. Listing never opens an image; every file is optional until it is asked for.
"""
from __future__ import annotations

import csv
import functools
import os
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from monolib.data import exact
from monolib.io import DataFileError, read_h5

SETTING_RE = re.compile(r"^ai_\d{3}_\d{3}$")
FRAME_RE = re.compile(r"^frame\.(\d{4})\.")
SCENE_DIR_RE = re.compile(r"^scene_(cam_\d{2})_(final_hdf5|geometry_hdf5|final_preview|geometry_preview)$")
SPLIT_CSV = "metadata_images_split_scene_v1.csv"
CAMERA_CSV = "metadata_camera_parameters.csv"
FOV_X = np.pi / 3


class HdrMissing(DataFileError):
    """A frame's `color.hdf5` is missing where its HDR radiance is needed; the message names the file."""


# ---- camera model ------------------------------------------------------------------------------------------

@functools.lru_cache(maxsize=16)
def _rays(M_cam_from_uv: tuple, height: int, width: int) -> np.ndarray:
    u = -1.0 + (2.0 * np.arange(width) + 1.0) / width
    v = 1.0 - (2.0 * np.arange(height) + 1.0) / height
    uv1 = np.stack(np.broadcast_arrays(u[None, :], v[:, None], np.ones((1, 1))), axis=-1)  # (H, W, 3)
    rays = exact.matmul(uv1, np.array(M_cam_from_uv, dtype=np.float64).T)
    rays.setflags(write=False)
    return rays


@dataclass(frozen=True)
class Camera:
    """Hypersim's camera: pixel (row i, col j) -> uv in [-1, 1] -> ray ``M_cam_from_uv @ (u, v, 1)``.

    Camera frame: +x right, +y up, +z backward (the camera looks along -z). Planar depth is ``-z``.
    """

    M_cam_from_uv: tuple  # 3x3 as nested tuples (hashable)
    meters_per_asset_unit: float = 1.0
    name: str = "canonical"

    @property
    def M(self) -> np.ndarray:
        return np.array(self.M_cam_from_uv, dtype=np.float64)

    @staticmethod
    def canonical(width: int = 1024, height: int = 768, meters_per_asset_unit: float = 1.0) -> "Camera":
        """Hypersim's default pinhole camera: 60 degree horizontal field of view, square pixels."""
        tx = np.tan(FOV_X / 2)
        ty = tx * height / width
        M = ((tx, 0.0, 0.0), (0.0, ty, 0.0), (0.0, 0.0, -1.0))
        return Camera(M, meters_per_asset_unit, "canonical")

    @property
    def is_canonical(self) -> bool:
        return bool(np.allclose(self.M, Camera.canonical().M, atol=1e-4))

    def rays(self, height: int, width: int) -> np.ndarray:
        """(H, W, 3) float64 camera-frame ray of each pixel centre (not normalised). Cached; do not modify."""
        return _rays(self.M_cam_from_uv, int(height), int(width))

    def planar_from_euclidean(self, distance: np.ndarray) -> np.ndarray:
        """Hypersim's `depth_meters` (distance along the ray) -> planar depth (metres in front of the camera)."""
        r = self.rays(*distance.shape)
        return (distance * (-r[..., 2] / np.linalg.norm(r, axis=-1))).astype(np.float32)

    def euclidean_from_planar(self, depth: np.ndarray) -> np.ndarray:
        r = self.rays(*depth.shape)
        return (depth * (np.linalg.norm(r, axis=-1) / -r[..., 2])).astype(np.float32)

    def backproject(self, depth: np.ndarray) -> np.ndarray:
        """Planar depth (H, W) in metres -> (H, W, 3) float32 points in the camera frame (NaN stays NaN)."""
        r = self.rays(*depth.shape)
        return (r * (depth / -r[..., 2])[..., None]).astype(np.float32)

    def backproject_masked(self, depth: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """The points (M, 3) of the pixels where `mask` holds (row-major order), without the full image."""
        r = self.rays(*depth.shape)[mask]
        return r * (depth[mask] / -r[:, 2])[:, None]


def camera_from_row(row: dict, name: str) -> Camera:
    M = tuple(tuple(float(row[f"M_cam_from_uv_{i}{j}"]) for j in range(3)) for i in range(3))
    scale = row.get("settings_units_info_meters_scale", "")
    return Camera(M, float(scale) if scale not in ("", None) else 1.0, name)


# ---- tonemap (scene_generate_images_tonemap.py) ------------------------------------------------------------

def tonemap(color: np.ndarray, valid: Optional[np.ndarray] = None) -> np.ndarray:
    """Hypersim's tonemap: scale so the 90th percentile of brightness maps to 0.8 after gamma 1/2.2 -> uint8.

    The gamma curve is applied by its thresholds: a scaled radiance x becomes the number of levels k = 1..255 with
    x >= ((k - 0.5) / 255) ** 2.2, which is round(255 x ** (1 / 2.2)) but computed with comparisons and `exact`
    arithmetic only, so the same colour gives the same bytes on every CPU."""
    color = np.asarray(color, dtype=np.float32)
    gamma, percentile, target = 1.0 / 2.2, 90, 0.8
    if valid is None:
        valid = np.ones(color.shape[:2], bool)
    if not valid.any():
        scale = 1.0
    else:
        brightness = 0.3 * color[..., 0] + 0.59 * color[..., 1] + 0.11 * color[..., 2]
        q = np.percentile(brightness[valid], percentile)
        scale = 0.0 if q < 1e-4 else float(exact.power(target, 1.0 / gamma)) / float(q)
    x = np.maximum(scale * color.astype(np.float64), 0.0)
    return np.searchsorted(_tonemap_thresholds(gamma), x, side="right").astype(np.uint8)


@functools.lru_cache(maxsize=4)
def _tonemap_thresholds(gamma: float) -> np.ndarray:
    """The 255 radiances at which `tonemap`'s output steps up one level: ((k - 0.5) / 255) ** (1 / gamma)."""
    out = exact.power((np.arange(1, 256) - 0.5) / 255.0, 1.0 / gamma)
    out.setflags(write=False)
    return out


# ---- frames ------------------------------------------------------------------------------------------------

class Frame:
    """One frame: lazily read modalities. Asking for a missing or corrupt file raises `DataFileError`."""

    def __init__(self, dataset: "HypersimDataset", setting: str, scene: str, index: int):
        self.dataset, self.setting, self.scene, self.index = dataset, setting, scene, int(index)
        base = dataset.root / setting / "images"
        stem = f"frame.{self.index:04d}"
        self.files = {
            "color": base / f"scene_{scene}_final_hdf5" / f"{stem}.color.hdf5",
            "depth_meters": base / f"scene_{scene}_geometry_hdf5" / f"{stem}.depth_meters.hdf5",
            "position": base / f"scene_{scene}_geometry_hdf5" / f"{stem}.position.hdf5",
            "semantic": base / f"scene_{scene}_geometry_hdf5" / f"{stem}.semantic.hdf5",
            "semantic_instance": base / f"scene_{scene}_geometry_hdf5" / f"{stem}.semantic_instance.hdf5",
            "render_entity_id": base / f"scene_{scene}_geometry_hdf5" / f"{stem}.render_entity_id.hdf5",
            "tonemap": base / f"scene_{scene}_final_preview" / f"{stem}.tonemap.jpg",
        }

    def __repr__(self) -> str:
        return f"Frame({self.setting}, {self.scene}, {self.index})"

    @property
    def key(self) -> str:
        """``ai_VVV_NNN/cam_XX/IIII``: a frame's name everywhere in the study."""
        return f"{self.setting}/{self.scene}/{self.index:04d}"

    @property
    def camera(self) -> Camera:
        return self.dataset.camera(self.setting)

    def _read(self, name: str, dtype, ndim: int) -> np.ndarray:
        arr = read_h5(self.files[name])
        if arr.ndim != ndim:
            raise DataFileError(f"{self.files[name]}: expected {ndim} dimensions, got shape {arr.shape}")
        return arr.astype(dtype)

    @functools.cached_property
    def depth_meters(self) -> np.ndarray:
        """Hypersim's own `depth_meters`: Euclidean distance from the camera centre, metres, NaN = invalid."""
        return self._read("depth_meters", np.float32, 2)

    @functools.cached_property
    def depth(self) -> np.ndarray:
        """(H, W) float32 **planar** depth in metres (the setting's own M_cam_from_uv); NaN where invalid."""
        return self.camera.planar_from_euclidean(self.depth_meters)

    def points_cam(self) -> np.ndarray:
        """(H, W, 3) float32 metres in the Hypersim camera frame (+x right, +y up, +z backward)."""
        return self.camera.backproject(self.depth)

    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        """(R_world_from_cam (3, 3), camera position in asset units (3,)) of this frame's keyframe."""
        cam_dir = self.dataset.root / self.setting / "_detail" / self.scene
        R = read_h5(cam_dir / "camera_keyframe_orientations.hdf5")
        t = read_h5(cam_dir / "camera_keyframe_positions.hdf5")
        if self.index >= len(R) or self.index >= len(t):
            raise DataFileError(f"{cam_dir}: no keyframe {self.index} (have {min(len(R), len(t))})")
        return R[self.index].astype(np.float64), t[self.index].astype(np.float64)

    def points_world(self) -> np.ndarray:
        """(H, W, 3) float32 **metres** in the world frame (z up)."""
        R, t = self.pose()
        mpau = self.dataset.meters_per_asset_unit(self.setting)
        p = self.points_cam().astype(np.float64) @ R.T + t * mpau
        return p.astype(np.float32)

    @functools.cached_property
    def rgb(self) -> Optional[np.ndarray]:
        """(H, W, 3) uint8, Hypersim's tonemap of the HDR colour; None when the colour file is missing."""
        if not self.files["color"].exists():
            return None
        color = self._read("color", np.float32, 3)
        valid = None
        if self.files["render_entity_id"].exists():
            valid = read_h5(self.files["render_entity_id"]) != -1
        return tonemap(color, valid)

    @functools.cached_property
    def hdr(self) -> np.ndarray:
        """(H, W, 3) float32: `color.hdf5` as stored, Hypersim's linear HDR radiance (what the original code's node
        colours are medians of). A missing file is `HdrMissing`: a graph of HDR colours cannot be built without it."""
        if not self.files["color"].exists():
            raise HdrMissing(f"{self.files['color']}: file not found; node colours of `graphs.colour: hdr` are medians "
                             f"of this file (a dataset without HDR colour needs `graphs.colour: tonemapped`)")
        return self._read("color", np.float32, 3)

    @functools.cached_property
    def semantic(self) -> Optional[np.ndarray]:
        """(H, W) int16 NYU40 ids, -1 unlabelled; None when the file is missing."""
        if not self.files["semantic"].exists():
            return None
        return self._read("semantic", np.int16, 2)


# ---- the dataset -------------------------------------------------------------------------------------------

class HypersimDataset:
    """Index of the settings / scenes / frames under `root` (folders ``ai_VVV_NNN``).

    Metadata CSVs (split, camera parameters) come from `metadata_dir` when given, else from `root`.
    """

    def __init__(self, root: str | os.PathLike, metadata_dir: str | os.PathLike | None = None):
        self.root = Path(root)
        if not self.root.is_dir():
            raise DataFileError(f"{self.root}: Hypersim root folder not found")
        self.metadata_dir = Path(metadata_dir) if metadata_dir else self.root
        self._frames: dict[tuple[str, str], list[int]] = {}
        folders = sorted(p.name for p in self.root.iterdir() if p.is_dir())
        odd = [n for n in folders if n.startswith("ai_") and not SETTING_RE.match(n)]
        if odd:  # a setting folder must be ai_VVV_NNN; say which were left out rather than drop them unseen
            warnings.warn(f"{self.root}: {len(odd)} folders that are not Hypersim setting names (ai_VVV_NNN) are "
                          f"ignored: {', '.join(odd[:4])}{' ...' if len(odd) > 4 else ''}")
        for setting in [n for n in folders if SETTING_RE.match(n)]:
            images = self.root / setting / "images"
            if not images.is_dir():
                continue
            per_scene: dict[str, set[int]] = {}
            for d in os.scandir(images):
                m = SCENE_DIR_RE.match(d.name)
                if not (m and d.is_dir()):
                    continue
                ids = per_scene.setdefault(m.group(1), set())
                for f in os.scandir(d.path):
                    fm = FRAME_RE.match(f.name)
                    if fm:
                        ids.add(int(fm.group(1)))
            for scene in sorted(per_scene):
                if per_scene[scene]:
                    self._frames[(setting, scene)] = sorted(per_scene[scene])
        self._split = self._read_split()
        self._cameras = self._read_cameras()
        self._warned: set[str] = set()

    # metadata
    def _read_split(self) -> dict[str, str]:
        path = self.metadata_dir / SPLIT_CSV
        if not path.exists():
            return {}
        votes: dict[str, dict[str, int]] = {}
        with open(path, newline="") as f:
            for row in csv.DictReader(f):
                part = (row.get("split_partition_name") or "").strip()
                if part and str(row.get("included_in_public_release", "True")).strip() == "True":
                    v = votes.setdefault(row["scene_name"].strip(), {})
                    v[part] = v.get(part, 0) + 1
        return {s: max(v, key=v.get) for s, v in votes.items()}

    def _read_cameras(self) -> dict[str, Camera]:
        path = self.metadata_dir / CAMERA_CSV
        if not path.exists():
            return {}
        cams = {}
        with open(path, newline="") as f:
            for row in csv.DictReader(f):
                try:
                    cams[row["scene_name"]] = camera_from_row(row, row["scene_name"])
                except (KeyError, ValueError) as exc:
                    raise DataFileError(f"{path}: row {row.get('scene_name')!r} has no valid M_cam_from_uv "
                                        f"({exc})") from exc
        return cams

    # index
    def settings(self, split: Optional[str] = None) -> list[str]:
        names = sorted({s for s, _ in self._frames})
        return [s for s in names if split is None or self._split.get(s) == split]

    def split(self, setting: str) -> Optional[str]:
        return self._split.get(setting)

    def scenes(self, setting: str) -> list[str]:
        return [c for s, c in self._frames if s == setting]

    def frame_ids(self, setting: str, scene: str) -> list[int]:
        return list(self._frames.get((setting, scene), []))

    def frames(self, setting: str) -> list[Frame]:
        return [self.frame(setting, c, i) for c in self.scenes(setting) for i in self.frame_ids(setting, c)]

    def frame(self, setting: str, scene: str, index: int) -> Frame:
        if (setting, scene) not in self._frames:
            raise DataFileError(f"{self.root / setting}: no scene {scene!r} with frames "
                                f"(scenes: {self.scenes(setting)})")
        return Frame(self, setting, scene, index)

    def frame_by_key(self, key: str) -> Frame:
        setting, scene, index = key.split("/")
        return self.frame(setting, scene, int(index))

    # cameras and units
    def camera(self, setting: str) -> Camera:
        cam = self._cameras.get(setting)
        if cam is None:
            if setting not in self._warned:
                warnings.warn(f"{setting}: no row in {self.metadata_dir / CAMERA_CSV}; "
                              "using the canonical 60-degree camera")
                self._warned.add(setting)
            return Camera.canonical(meters_per_asset_unit=self.meters_per_asset_unit(setting, fallback=False))
        return cam

    def meters_per_asset_unit(self, setting: str, fallback: bool = True) -> float:
        """From ``_detail/metadata_scene.csv``; else the camera CSV's ``settings_units_info_meters_scale``."""
        path = self.root / setting / "_detail" / "metadata_scene.csv"
        if path.exists():
            with open(path, newline="") as f:
                for row in csv.DictReader(f):
                    if row.get("parameter_name", "").strip() == "meters_per_asset_unit":
                        return float(row["parameter_value"])
            raise DataFileError(f"{path}: no row meters_per_asset_unit")
        if fallback and setting in self._cameras:
            return self._cameras[setting].meters_per_asset_unit
        if not fallback:
            return 1.0
        raise DataFileError(f"{path}: file not found, and no row for {setting} in {self.metadata_dir / CAMERA_CSV}")
