"""The procedural mini-Hypersim: furnished rooms, ray cast with embree, written in Hypersim's exact layout.

Words (design.md): a *setting* is one room configuration (folder ``ai_VVV_NNN``), a *scene* one camera trajectory
(``cam_XX``), a *frame* one image of it. A *family* is one volume ``ai_9FF``: its settings share the room type, the
furniture catalogue (object types and their dimensions), the materials, doors and windows, and differ in layout,
lighting and viewpoints -- the paper's "two neighbouring offices". Volumes start at 900 so a synthetic setting can
never be confused with a real Hypersim scene.

What makes it look like Hypersim where place recognition is decided (../shared/docs/real-hypersim-statistics.md;
`monolib.graphs.fidelity` measures it for every study): each family has its own paints, woods, tiles and fabrics drawn from
a wide continuous space, so walls and floors of two places differ more than one wall seen twice; surfaces carry
clutter (vases, bottles, bowls, books, table lamps), floors carry plants, some families have skirting boards and
pendant lamps; the cameras of a setting dwell on one part of the room (`make_trajectories`) with one exposure per
scene, and some of them look up enough to show the ceiling. The test split holds one setting per family (the
`paper` protocol) and, for the first `test_siblings` families, a sibling setting (the `siblings` protocol).

Everything is built in metres in a z-up world with the floor at z = 0; positions and camera centres are converted to
the setting's asset units (``meters_per_asset_unit`` = 0.01 or 0.0254) when written, as in Hypersim
(../shared/docs/hypersim-format.md sections 1, 1a, 1b, 2, 3, 6, 7).

Public API: `render_dataset(study, out_dir)` and `benchmark()`.
"""
from __future__ import annotations

import csv
import hashlib
import io as _io
import json
import math
import multiprocessing as mp
import os
import shutil
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from monolib.data.hypersim import Camera, tonemap
from monolib.data.labels import ID
from monolib.io import atomic_path, move_aside, write_h5, write_json, write_text
from monolib.progress import tqdm
from monolib.versions import code_version

VOLUME0 = 900  # families are volumes ai_900, ai_901, ... wrapping to ai_000 after ai_999 (3 digits, as in Hypersim)
FORMAT_VERSION = 4  # bump when the generator changes: finished settings with another version are re-rendered
FOV_X = math.pi / 3
H5_COMPRESSION = 4  # gzip level (Hypersim uses 9; 4 halves the write time at ~1% larger files)
N_PROP_MATERIALS = 4  # colours of a family's small props

# ai_037_002's tilt-shift camera (metadata_camera_parameters.csv of ml-hypersim)
TILT_SHIFT_M = ((0.579607251426182, 0.0, -0.06955286861651404),
                (0.0, 0.4346865334657201, 0.09273312506660672),
                (-0.0, 0.004054126980668954, -1.003909173803896))
TILT_SHIFT_PROJ = (1.7253062268275619, 0.001113868662274642, -0.11942983282195321, 0.0,
                   0.0, 2.2985281393428907, 0.21231970279458348, 0.0,
                   0.0, 0.009300822120943601, -0.9972411188430887, -2.002002002002002,
                   0.0, 0.009282239059762895, -0.9952486290951505, 0.0)

# Hypersim's metadata_camera_parameters.csv columns (contrib/mikeroberts3000), names only
CAMERA_COLUMNS = (
    "scene_name,settings_output_img_height,settings_output_img_width,settings_units_info_meters_scale,"
    "use_camera_physical,camera_physical_anisotropy,camera_physical_blades_enable,camera_physical_blades_num,"
    "camera_physical_blades_rotation,camera_physical_bmpaperture_affects_exposure,camera_physical_bmpaperture_enable,"
    "camera_physical_bmpaperture_resolution,camera_physical_bmpaperture_tex,camera_physical_center_bias,"
    "camera_physical_distortion,camera_physical_distortion_tex,camera_physical_distortion_type,"
    "camera_physical_dof_display_threshold,camera_physical_dont_affect_settings,"
    "camera_physical_enable_thin_lens_equation,camera_physical_exposure,camera_physical_f_number,"
    "camera_physical_film_width,camera_physical_focal_length,camera_physical_focus_distance,camera_physical_fov,"
    "camera_physical_horizontal_offset,camera_physical_horizontal_shift,camera_physical_ISO,camera_physical_latency,"
    "camera_physical_lens_file,camera_physical_lens_shift,camera_physical_optical_vignetting,"
    "camera_physical_rolling_shutter_duration,camera_physical_rolling_shutter_mode,camera_physical_shutter_angle,"
    "camera_physical_shutter_offset,camera_physical_shutter_speed,camera_physical_specify_focus,"
    "camera_physical_specify_fov,camera_physical_subdivs,camera_physical_target_distance,camera_physical_targeted,"
    "camera_physical_type,camera_physical_use_dof,camera_physical_use_moblur,camera_physical_vertical_offset,"
    "camera_physical_vignetting,camera_physical_white_balance,camera_physical_zoom_factor,"
    "settings_camera_auto_corrections_mode,settings_camera_auto_exposure,settings_camera_auto_exposure_compensation,"
    "settings_camera_auto_fit,settings_camera_auto_white_balance,settings_camera_curve,settings_camera_dist,"
    "settings_camera_dont_affect_settings,settings_camera_fov,settings_camera_height,settings_camera_image_planes,"
    "settings_camera_type,M_cam_from_uv_00,M_cam_from_uv_01,M_cam_from_uv_02,M_cam_from_uv_10,M_cam_from_uv_11,"
    "M_cam_from_uv_12,M_cam_from_uv_20,M_cam_from_uv_21,M_cam_from_uv_22,M_proj_00,M_proj_01,M_proj_02,M_proj_03,"
    "M_proj_10,M_proj_11,M_proj_12,M_proj_13,M_proj_20,M_proj_21,M_proj_22,M_proj_23,M_proj_30,M_proj_31,M_proj_32,"
    "M_proj_33"
).split(",")
SPLIT_COLUMNS = ["scene_name", "camera_name", "frame_id", "included_in_public_release", "exclude_reason",
                 "split_partition_name"]
TRAJECTORY_COLUMNS = ["Animation", "Rendering job (geometry)", "Instance type (geometry)", "Rendering job (pre)",
                      "Instance type (pre)", "Rendering job (final)", "Instance type (final)", "Scene type", "Notes",
                      "Any good views of scene?"]

ROOM_TYPES = ["office", "bedroom", "living room", "kitchen", "bathroom", "classroom", "dining room", "library"]
SCENE_TYPE_LABEL = {"office": "Office", "bedroom": "Bedroom", "living room": "Living room", "kitchen": "Kitchen",
                    "bathroom": "Bathroom", "classroom": "Classroom", "dining room": "Dining room",
                    "library": "Library"}


# =============================================================================================================
# materials
# =============================================================================================================

PAINT, WOOD, FABRIC, TILES, PICTURE, BOOKS, PLAIN, STONE, GLASS, RUG = range(10)


@dataclass
class Material:
    kind: int
    base: tuple
    alt: tuple = (0.0, 0.0, 0.0)
    scale: float = 1.0
    seed: float = 0.0
    emission: tuple = (0.0, 0.0, 0.0)


def _hsv(h: float, s: float, v: float) -> tuple:
    import colorsys

    return tuple(float(c) ** 2.2 for c in colorsys.hsv_to_rgb(h % 1.0, s, v))  # sRGB-ish -> linear albedo


def _family_materials(rng: np.random.Generator, room: str) -> dict[str, Material]:
    """One family's materials, drawn from a wide continuous space of paints, woods, tiles and fabrics.

    Every setting of the family (siblings included) uses exactly these; two families almost never share a wall or
    floor colour. Real Hypersim rooms differ this way: between two places the wall and floor colours spread 2.6
    times more than between two frames of one place (../shared/docs/real-hypersim-statistics.md).
    """
    u = rng.uniform

    def paint(sat_hi=0.65, v=(0.3, 0.95)) -> Material:
        # a third of the paints are near-neutral (white, grey, beige), the rest carry a colour
        sat = u(0.0, 0.08) if u() < 0.33 else u(0.1, sat_hi)
        return Material(PAINT, _hsv(u(0, 1), sat, u(*v)), seed=u(0, 100))

    def wood(v=(0.25, 0.85)) -> Material:
        val = u(*v)
        return Material(WOOD, _hsv(u(0.03, 0.11), u(0.3, 0.75), val), _hsv(u(0.03, 0.1), u(0.45, 0.85), val * 0.55),
                        u(40, 110), u(0, 100))

    def fabric(scale=(150, 320)) -> Material:
        return Material(FABRIC, _hsv(u(0, 1), u(0.05, 0.6), u(0.25, 0.85)), scale=u(*scale), seed=u(0, 100))

    def tiles() -> Material:
        h, v = u(0, 1), u(0.35, 0.9)
        return Material(TILES, _hsv(h, u(0.0, 0.4), v), _hsv(h, 0.05, v * 0.55), u(0.2, 0.5), u(0, 100))

    def rug() -> Material:
        h = u(0, 1)
        return Material(RUG, _hsv(h, u(0.15, 0.6), u(0.25, 0.75)), _hsv(h + u(-0.15, 0.15), u(0.1, 0.5), u(0.4, 0.85)),
                        u(200, 400), u(0, 100))

    def stone() -> Material:
        h, v = u(0.0, 1.0), u(0.35, 0.9)
        return Material(STONE, _hsv(h, u(0.02, 0.2), v), _hsv(h, 0.1, v * 0.7), u(60, 120), u(0, 100))

    m: dict[str, Material] = {}
    r = u()
    m["wall"] = paint() if r < 0.8 else (wood((0.35, 0.8)) if r < 0.9 else stone())
    m["wall2"] = paint()  # a feature wall (half of the families paint one wall differently)
    m["ceiling"] = Material(PAINT, _hsv(u(0.05, 0.15), u(0.0, 0.08), u(0.8, 0.95)), seed=3.0)
    if room in ("kitchen", "bathroom"):
        m["floor"] = tiles() if u() < 0.75 else stone()
    else:
        r = u()
        m["floor"] = wood() if r < 0.5 else (rug() if r < 0.75 else (tiles() if r < 0.9 else stone()))
    m["door"] = wood() if u() < 0.6 else paint(0.5, (0.2, 0.95))
    m["frame"] = Material(PAINT, _hsv(u(0, 1), u(0.0, 0.1), u(0.7, 0.95)), seed=2.0)
    m["skirting"] = m["frame"] if u() < 0.5 else wood()
    m["glass"] = Material(GLASS, (0.05, 0.05, 0.05), emission=(1.0, 1.1, 1.3))
    m["wood"] = wood()
    m["wood2"] = wood() if u() < 0.5 else paint(0.6, (0.2, 0.95))
    m["fabric"] = fabric()
    m["fabric2"] = fabric()
    m["pillow"] = fabric()
    m["metal"] = Material(PLAIN, _hsv(0.6, 0.03, u(0.2, 0.75)))
    m["white"] = Material(PLAIN, _hsv(0.6, 0.02, 0.92))
    m["appliance"] = paint(0.5, (0.3, 0.9)) if u() < 0.3 else Material(PLAIN, _hsv(0.6, 0.02, u(0.75, 0.9)))
    m["screen"] = Material(PLAIN, (0.01, 0.01, 0.012))
    m["books"] = Material(BOOKS, (0.5, 0.3, 0.2), scale=u(0.025, 0.045), seed=u(0, 100))
    m["stone"] = stone()
    m["board"] = Material(PLAIN, (0.92, 0.93, 0.93))
    m["mat"] = rug()
    m["cardboard"] = Material(PLAIN, _hsv(0.085, 0.5, 0.65))
    m["shade"] = Material(FABRIC, _hsv(u(0.05, 0.15), u(0.05, 0.3), 0.9), scale=300, seed=u(0, 100),
                          emission=(0.6, 0.5, 0.35))
    m["towel"] = fabric()
    m["curtain"] = fabric((15, 30))
    for k in range(N_PROP_MATERIALS):  # vases, bottles, bowls, plant pots: the family's own small things
        m[f"prop{k}"] = Material(PAINT, _hsv(u(0, 1), u(0.1, 0.8), u(0.2, 0.95)), seed=u(0, 100))
    m["leaves"] = Material(FABRIC, _hsv(u(0.22, 0.4), u(0.4, 0.8), u(0.25, 0.6)), scale=u(60, 120), seed=u(0, 100))
    m["paper"] = Material(PLAIN, (0.85, 0.85, 0.82))
    m["mirror"] = Material(PLAIN, (0.55, 0.6, 0.62), emission=(0.05, 0.05, 0.06))
    for k in range(3):
        m[f"picture{k}"] = Material(PICTURE, _hsv(u(0, 1), u(0.3, 0.8), u(0.3, 0.9)),
                                    _hsv(u(0, 1), u(0.3, 0.8), u(0.3, 0.9)), u(2, 7), u(0, 100))
    return m


def _hash(*xs: np.ndarray, seed: float = 0.0) -> np.ndarray:
    """A cheap deterministic hash of integer lattice coordinates -> [0, 1)."""
    s = seed * 0.731 + 0.1
    for i, x in enumerate(xs):
        s = s + np.asarray(x, np.float64) * (12.9898 + 31.4159 * i)
    return np.mod(np.sin(s) * 43758.5453, 1.0)


def _wave_noise(p: np.ndarray, seed: float, freq: float) -> np.ndarray:
    """Smooth noise in [-1, 1] from three seeded plane waves (vectorised)."""
    out = np.zeros(len(p))
    r = np.random.default_rng(int(seed * 1000) % (2 ** 31))
    for k in range(3):
        d = r.normal(size=3)
        d /= np.linalg.norm(d)
        out += np.sin(p @ d * freq * (1.0 + 0.7 * k) + r.uniform(0, 6.28))
    return out / 3.0


def _albedo(mat: Material, p: np.ndarray) -> np.ndarray:
    """(n, 3) albedo of material `mat` at local points p (n, 3) in metres."""
    base = np.asarray(mat.base)
    alt = np.asarray(mat.alt)
    n = len(p)
    if mat.kind == PAINT:
        return base * (1.0 + 0.04 * _wave_noise(p, mat.seed, 3.0))[:, None]
    if mat.kind == WOOD:
        t = (p[:, 1] * 0.7 + p[:, 2]) * mat.scale + 2.5 * _wave_noise(p, mat.seed, 2.0) + 4 * np.sin(p[:, 0] * 1.3)
        g = (0.5 + 0.5 * np.sin(t)) ** 3
        plank = _hash(np.floor(p[:, 1] / 0.18), seed=mat.seed)[:, None] * 0.2 + 0.9
        g = 0.6 * g[:, None]
        return (base * (1 - g) + alt * g) * plank
    if mat.kind == FABRIC:
        w = np.sin(p[:, 0] * mat.scale) * np.sin((p[:, 1] + p[:, 2]) * mat.scale)
        return base * (0.9 + 0.06 * w + 0.06 * _wave_noise(p, mat.seed, 6.0))[:, None]
    if mat.kind == TILES:
        s = mat.scale
        fx, fy = np.mod(p[:, 0] / s, 1.0), np.mod(p[:, 1] / s, 1.0)
        grout = (np.minimum(fx, fy) < 0.035)[:, None]
        var = 0.92 + 0.16 * _hash(np.floor(p[:, 0] / s), np.floor(p[:, 1] / s), seed=mat.seed)[:, None]
        return np.where(grout, alt, base * var)
    if mat.kind == PICTURE:
        cu, cv = np.floor(p[:, 0] * mat.scale), np.floor(p[:, 2] * mat.scale * 0.8)
        h = _hash(cu, cv, seed=mat.seed)[:, None]
        h2 = _hash(cu + 7, cv - 3, seed=mat.seed)[:, None]
        wave = (0.5 + 0.5 * np.sin(p[:, 0] * 9 + p[:, 2] * 5 + mat.seed))[:, None]
        col = base * h + alt * (1 - h)
        return np.clip(col * (0.5 + 0.6 * wave) + 0.25 * h2 * (1 - base), 0.0, 1.0)
    if mat.kind == BOOKS:
        k = np.floor(p[:, 0] / mat.scale)
        h = np.stack([_hash(k, seed=mat.seed + j) for j in range(3)], 1)
        return 0.05 + 0.55 * h ** 1.5
    if mat.kind == STONE:
        speck = _hash(np.floor(p[:, 0] * mat.scale), np.floor(p[:, 1] * mat.scale), np.floor(p[:, 2] * mat.scale),
                      seed=mat.seed)[:, None]
        return base * (0.85 + 0.3 * speck)
    if mat.kind == RUG:
        border = np.minimum(np.abs(np.mod(p[:, 0] * 2.0, 1.0) - 0.5), np.abs(np.mod(p[:, 1] * 2.0, 1.0) - 0.5))
        stripe = (border > 0.42)[:, None]
        w = np.sin(p[:, 0] * mat.scale) * np.sin(p[:, 1] * mat.scale)
        return np.where(stripe, alt, base) * (0.9 + 0.08 * w)[:, None]
    return np.broadcast_to(base, (n, 3)).astype(np.float64)


# =============================================================================================================
# geometry: parts, objects, the room
# =============================================================================================================

def _box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box (vertices (8,3), faces (12,3)) from corner lo to corner hi."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    v = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return v, f


def _bx(cx, cy, z0, sx, sy, sz):
    """Box centred at (cx, cy) in x/y, from height z0 up by sz."""
    return _box((cx - sx / 2, cy - sy / 2, z0), (cx + sx / 2, cy + sy / 2, z0 + sz))


def _cyl(cx, cy, z0, r, h, sections=14):
    a = np.linspace(0, 2 * np.pi, sections, endpoint=False)
    ring = np.stack([cx + r * np.cos(a), cy + r * np.sin(a)], 1)
    v = np.concatenate([np.c_[ring, np.full(sections, z0)], np.c_[ring, np.full(sections, z0 + h)],
                        [[cx, cy, z0], [cx, cy, z0 + h]]])
    f = []
    for i in range(sections):
        j = (i + 1) % sections
        f += [[i, j, sections + j], [i, sections + j, sections + i],
              [2 * sections, j, i], [2 * sections + 1, sections + i, sections + j]]
    return v, np.array(f)


@dataclass
class Obj:
    """One semantic instance: several mesh parts in the object's local frame (+y = front, z up)."""
    sem: int
    parts: list  # list of ((v, f), material key)


@dataclass
class Item:
    """A placed piece of furniture: objects, footprint (w, d) and pose (x, y, yaw, z0) in the room."""
    kind: str
    objs: list
    w: float
    d: float
    h: float
    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0
    z0: float = 0.0


# ---- furniture builders: local frame, footprint centred at the origin, front towards +y ----------------------

def _legs(w, d, h, t, inset=0.03):
    return [_bx(sx * (w / 2 - inset - t / 2), sy * (d / 2 - inset - t / 2), 0, t, t, h) for sx in (-1, 1) for sy in (-1, 1)]


def b_table(dim, mats, sem="table"):
    w, d, h = dim
    parts = [(_bx(0, 0, h - 0.04, w, d, 0.04), mats.get("top", "wood"))]
    parts += [(leg, mats.get("legs", "wood")) for leg in _legs(w, d, h - 0.04, 0.05)]
    return [Obj(ID[sem], parts)]


def b_desk(dim, mats):
    w, d, h = dim
    parts = [(_bx(0, 0, h - 0.035, w, d, 0.035), "wood"),
             (_bx(-w / 2 + 0.02, 0, 0, 0.03, d - 0.04, h - 0.035), "wood2"),
             (_bx(w / 2 - 0.22, 0, 0.05, 0.4, d - 0.06, h - 0.09), "wood2"),
             (_bx(0, -d / 2 + 0.03, 0.3, w - 0.1, 0.02, h - 0.34), "wood2")]
    return [Obj(ID["desk"], parts)]


def b_chair(dim, mats):
    w, d, h = dim
    seat = 0.45
    parts = [(_bx(0, 0, seat - 0.05, w, d, 0.05), "fabric"),
             (_bx(0, -d / 2 + 0.03, seat, w, 0.05, h - seat), "fabric")]
    parts += [(leg, "metal") for leg in _legs(w, d, seat - 0.05, 0.035, 0.02)]
    return [Obj(ID["chair"], parts)]


def b_sofa(dim, mats):
    w, d, h = dim
    arm = 0.18
    parts = [(_bx(0, 0.05, 0.08, w - 2 * arm, d - 0.2, 0.35), "fabric"),
             (_bx(0, -d / 2 + 0.1, 0.08, w, 0.2, h - 0.08), "fabric"),
             (_bx(-w / 2 + arm / 2, 0.05, 0.08, arm, d - 0.1, 0.55), "fabric"),
             (_bx(w / 2 - arm / 2, 0.05, 0.08, arm, d - 0.1, 0.55), "fabric"),
             (_bx(0, 0, 0, w - 0.1, d - 0.1, 0.08), "wood")]
    objs = [Obj(ID["sofa"], parts)]
    for sx in (-1, 1):
        objs.append(Obj(ID["pillow"], [(_bx(sx * (w / 2 - arm - 0.3), -d / 2 + 0.3, 0.43, 0.42, 0.14, 0.38), "pillow")]))
    return objs


def b_bed(dim, mats):
    w, d, h = dim
    parts = [(_bx(0, 0, 0, w, d, 0.3), "wood"), (_bx(0, 0.02, 0.3, w - 0.06, d - 0.1, 0.22), "fabric"),
             (_bx(0, -d / 2 + 0.04, 0, w, 0.08, h), "wood")]
    objs = [Obj(ID["bed"], parts)]
    n = 2 if w > 1.2 else 1
    for k in range(n):
        cx = (k - (n - 1) / 2) * (w / 2)
        objs.append(Obj(ID["pillow"], [(_bx(cx, -d / 2 + 0.3, 0.52, min(0.6, w / n - 0.1), 0.35, 0.14), "pillow")]))
    return objs


def b_boxlike(sem, mat, handles=True):
    def build(dim, mats):
        w, d, h = dim
        parts = [(_bx(0, 0, 0, w, d, h), mats.get("body", mat))]
        if handles:
            nd = max(1, int(h / 0.3))
            for k in range(nd):
                parts.append((_bx(0, d / 2 + 0.005, (k + 0.5) * h / nd - 0.01, min(0.2, w * 0.4), 0.012, 0.02), "metal"))
        return [Obj(ID[sem], parts)]
    return build


def b_bookshelf(dim, mats, sem="bookshelf", books=True):
    w, d, h = dim
    t = 0.025
    frame = [(_bx(-w / 2 + t / 2, 0, 0, t, d, h), "wood"), (_bx(w / 2 - t / 2, 0, 0, t, d, h), "wood"),
             (_bx(0, -d / 2 + 0.005, 0, w, 0.01, h), "wood")]
    nshelf = max(2, int(h / 0.38))
    objs = []
    for k in range(nshelf + 1):
        z = k * (h - t) / nshelf
        frame.append((_bx(0, 0, z, w - 2 * t, d, t), "wood"))
        if books and k < nshelf:
            bh = min(0.3, (h - t) / nshelf - 0.06)
            bw = (w - 2 * t) * (0.5 + 0.45 * ((k * 7919) % 10) / 10)
            objs.append(Obj(ID["books"], [(_bx(-w / 2 + t + bw / 2, 0.01, z + t, bw, d * 0.8, bh), "books")]))
    return [Obj(ID[sem], frame)] + objs


def b_counter(dim, mats):
    w, d, h = dim
    objs = [Obj(ID["cabinet"], [(_bx(0, -0.02, 0.08, w, d - 0.04, h - 0.12), "wood2"),
                                (_bx(0, -0.05, 0, w - 0.04, d - 0.1, 0.08), "metal")]
                + [(_bx(-w / 2 + (k + 0.5) * w / max(1, int(w / 0.5)), d / 2 - 0.03, h - 0.2, 0.12, 0.015, 0.02), "metal")
                   for k in range(max(1, int(w / 0.5)))]),
            Obj(ID["counter"], [(_bx(0, 0, h - 0.04, w + 0.02, d, 0.04), "stone")])]
    return objs


def b_kitchen_sink(dim, mats):
    objs = b_counter(dim, mats)
    w, d, h = dim
    objs.append(Obj(ID["sink"], [(_bx(0, 0.02, h, 0.55, 0.42, 0.015), "metal"),
                                 (_cyl(0, -d / 2 + 0.08, h, 0.02, 0.3), "metal")]))
    return objs


def b_vanity(dim, mats):
    w, d, h = dim
    return [Obj(ID["cabinet"], [(_bx(0, 0, 0, w, d, h - 0.03), "wood2")]),
            Obj(ID["sink"], [(_bx(0, 0, h - 0.03, w + 0.02, d + 0.02, 0.03), "white"),
                             (_bx(0, 0.04, h, w * 0.6, d * 0.55, 0.08), "white"),
                             (_cyl(0, -d / 2 + 0.06, h, 0.018, 0.22), "metal")])]


def b_toilet(dim, mats):
    w, d, h = dim
    return [Obj(ID["toilet"], [(_cyl(0, 0.06, 0, 0.16, 0.38), "white"), (_bx(0, 0.08, 0.38, w * 0.9, d * 0.6, 0.04), "white"),
                               (_bx(0, -d / 2 + 0.1, 0.38, w, 0.2, 0.4), "white")])]


def b_bathtub(dim, mats):
    w, d, h = dim
    t = 0.07
    return [Obj(ID["bathtub"], [(_bx(0, 0, 0, w, d, h - 0.1), "white"),
                                (_bx(0, -d / 2 + t / 2, h - 0.1, w, t, 0.1), "white"),
                                (_bx(0, d / 2 - t / 2, h - 0.1, w, t, 0.1), "white"),
                                (_bx(-w / 2 + t / 2, 0, h - 0.1, t, d, 0.1), "white"),
                                (_bx(w / 2 - t / 2, 0, h - 0.1, t, d, 0.1), "white")])]


def b_fridge(dim, mats):
    w, d, h = dim
    return [Obj(ID["refrigerator"], [(_bx(0, 0, 0, w, d, h), "appliance"),
                                     (_bx(w / 2 - 0.06, d / 2 + 0.01, h * 0.45, 0.03, 0.03, h * 0.35), "metal")])]


def b_tvstand(dim, mats):
    w, d, h = dim
    tw = min(w * 0.9, 1.3)
    return [Obj(ID["otherfurniture"], [(_bx(0, 0, 0, w, d, h), "wood2")]),
            Obj(ID["television"], [(_bx(0, -0.02, h + 0.08, tw, 0.05, tw * 0.58), "screen"),
                                   (_bx(0, -0.02, h, 0.25, 0.15, 0.08), "metal")])]


def b_nightstand(dim, mats):
    w, d, h = dim
    return [Obj(ID["nightstand"], [(_bx(0, 0, 0, w, d, h), "wood"),
                                   (_bx(0, d / 2 + 0.005, h * 0.6, 0.12, 0.01, 0.02), "metal")]),
            Obj(ID["lamp"], [(_cyl(0, 0, h, 0.07, 0.03), "metal"), (_cyl(0, 0, h + 0.03, 0.015, 0.25), "metal"),
                             (_cyl(0, 0, h + 0.22, 0.15, 0.2), "shade")])]


def b_floorlamp(dim, mats):
    w, d, h = dim
    return [Obj(ID["lamp"], [(_cyl(0, 0, 0, 0.15, 0.03), "metal"), (_cyl(0, 0, 0.03, 0.015, h - 0.3), "metal"),
                             (_cyl(0, 0, h - 0.35, 0.2, 0.35), "shade")])]


def b_dresser(dim, mats):
    objs = b_boxlike("dresser", "wood")(dim, mats)
    w, d, h = dim
    objs.append(Obj(ID["otherprop"], [(_cyl(w / 4, 0, h, 0.06, 0.25), "prop0")]))
    return objs


def b_shelves(dim, mats):
    w, d, h = dim
    objs = [Obj(ID["shelves"], [(_bx(0, 0, z, w, d, 0.025), "wood") for z in np.linspace(0, h, 3)])]
    objs.append(Obj(ID["box"], [(_bx(-w / 4, 0, h / 2 + 0.025, 0.3, d * 0.8, min(0.25, h / 2 - 0.05)), "cardboard")]))
    objs.append(Obj(ID["otherprop"], [(_cyl(w / 4, 0, 0.025, 0.05, 0.18), "prop0")]))
    objs.append(Obj(ID["books"], [(_bx(w / 4, 0, h + 0.025, 0.3, d * 0.8, 0.22), "books")]))
    return objs


def b_boxes(dim, mats):
    w, d, h = dim
    return [Obj(ID["box"], [(_bx(0, 0, 0, w, d, h), "cardboard")]),
            Obj(ID["box"], [(_bx(0.03, -0.02, h, w * 0.7, d * 0.7, h * 0.6), "cardboard")])]


def b_floormat(dim, mats):
    w, d, h = dim
    return [Obj(ID["floormat"], [(_bx(0, 0, 0, w, d, 0.012), "mat")])]


def b_coffee_table(dim, mats):
    objs = b_table(dim, {})
    w, d, h = dim
    objs.append(Obj(ID["otherprop"], [(_cyl(w / 5, 0, h, 0.05, 0.22), "prop0")]))
    objs.append(Obj(ID["paper"], [(_bx(-w / 5, 0, h, 0.3, 0.22, 0.005), "paper")]))
    return objs


def b_plant(dim, mats):
    """A potted plant on the floor: pot and foliage are one small thing (NYU40 otherprop, as in Hypersim)."""
    w, d, h = dim
    return [Obj(ID["otherprop"], [(_cyl(0, 0, 0, w * 0.3, h * 0.3), "prop1"),
                                  (_cyl(0, 0, h * 0.3, w * 0.5, h * 0.7, 8), "leaves")])]


def b_side_table(dim, mats):
    return b_table(dim, {"top": "wood2", "legs": "wood2"})


def b_lounge_chair(dim, mats):
    w, d, h = dim
    parts = [(_bx(0, 0.03, 0.1, w - 0.1, d - 0.1, 0.32), "fabric2"), (_bx(0, -d / 2 + 0.08, 0.1, w, 0.16, h - 0.1), "fabric2"),
             (_bx(-w / 2 + 0.05, 0.03, 0.1, 0.1, d - 0.1, 0.52), "fabric2"), (_bx(w / 2 - 0.05, 0.03, 0.1, 0.1, d - 0.1, 0.52), "fabric2")]
    parts += [(leg, "wood") for leg in _legs(w, d, 0.1, 0.04, 0.04)]
    return [Obj(ID["chair"], parts)]


def b_work_desk(dim, mats):
    objs = b_desk(dim, mats)
    w, d, h = dim
    objs.append(Obj(ID["paper"], [(_bx(-w / 5, 0.05, h, 0.3, 0.22, 0.004), "paper")]))
    objs.append(Obj(ID["otherprop"], [(_bx(0, -d / 2 + 0.2, h, 0.5, 0.05, 0.32), "screen"),
                                      (_bx(0, -d / 2 + 0.2, h, 0.1, 0.1, 0.06), "metal")]))
    return objs


# ---- wall-mounted things (local frame: x along the wall, +y out of the wall, z up from the mount height) ---------

def w_picture(dim, mats, key="picture0"):
    w, d, h = dim
    return [Obj(ID["picture"], [(_bx(0, 0.015, 0, w + 0.06, 0.03, h + 0.06), "wood2"), (_bx(0, 0.035, 0.03, w, 0.01, h), key)])]


def w_simple(sem, mat, thick=0.02):
    def build(dim, mats):
        w, d, h = dim
        return [Obj(ID[sem], [(_bx(0, thick / 2, 0, w, thick, h), mat)])]
    return build


def w_whiteboard(dim, mats):
    w, d, h = dim
    return [Obj(ID["whiteboard"], [(_bx(0, 0.015, 0, w, 0.03, h), "board"),
                                   (_bx(0, 0.05, -0.03, w, 0.06, 0.03), "metal")])]


def w_towel(dim, mats):
    w, d, h = dim
    return [Obj(ID["otherprop"], [(_cyl(-w / 2 - 0.05, 0.05, h, 0.012, 0.04), "metal")]),
            Obj(ID["towel"], [(_bx(0, 0.05, 0, w, 0.03, h), "towel")])]


# kind -> (builder, placement, dims (lo, hi) of width / depth / height in metres)
CATALOGUE = {
    "table": (b_table, "centre", ((1.0, 0.7, 0.72), (1.8, 1.0, 0.78))),
    "dining_table": (b_table, "centre", ((1.2, 0.8, 0.72), (2.0, 1.0, 0.78))),
    "coffee_table": (b_coffee_table, "centre", ((0.8, 0.5, 0.38), (1.2, 0.7, 0.48))),
    "desk": (b_work_desk, "wall", ((1.1, 0.6, 0.72), (1.6, 0.8, 0.76))),
    "student_desk": (b_desk, "grid", ((0.9, 0.5, 0.7), (1.2, 0.6, 0.74))),
    "chair": (b_chair, "near", ((0.42, 0.42, 0.85), (0.5, 0.5, 1.0))),
    "sofa": (b_sofa, "wall", ((1.6, 0.85, 0.8), (2.4, 1.0, 0.95))),
    "armchair": (b_sofa, "free", ((0.8, 0.8, 0.8), (1.0, 0.9, 0.95))),
    "bed": (b_bed, "wall", ((1.0, 1.95, 0.9), (1.8, 2.1, 1.2))),
    "nightstand": (b_nightstand, "wall", ((0.4, 0.35, 0.45), (0.55, 0.45, 0.6))),
    "dresser": (b_dresser, "wall", ((0.8, 0.45, 0.8), (1.4, 0.55, 1.1))),
    "cabinet": (b_boxlike("cabinet", "wood2"), "wall", ((0.6, 0.4, 0.8), (1.2, 0.5, 1.9))),
    "wardrobe": (b_boxlike("cabinet", "wood"), "wall", ((1.0, 0.55, 1.9), (1.6, 0.6, 2.2))),
    "bookshelf": (b_bookshelf, "wall", ((0.8, 0.3, 1.5), (1.2, 0.38, 2.1))),
    "shelves": (b_shelves, "wall_high", ((0.8, 0.25, 0.45), (1.2, 0.3, 0.6))),
    "counter": (b_counter, "wall", ((1.2, 0.6, 0.9), (2.4, 0.65, 0.92))),
    "kitchen_sink": (b_kitchen_sink, "wall", ((1.0, 0.6, 0.9), (1.4, 0.65, 0.92))),
    "fridge": (b_fridge, "wall", ((0.6, 0.65, 1.7), (0.8, 0.7, 1.95))),
    "upper_cabinet": (b_boxlike("cabinet", "wood2", False), "wall_high", ((1.0, 0.35, 0.6), (1.8, 0.38, 0.75))),
    "tvstand": (b_tvstand, "wall", ((1.2, 0.4, 0.45), (1.8, 0.5, 0.6))),
    "floorlamp": (b_floorlamp, "corner", ((0.4, 0.4, 1.5), (0.45, 0.45, 1.8))),
    "boxes": (b_boxes, "wall", ((0.35, 0.3, 0.25), (0.6, 0.45, 0.45))),
    "floormat": (b_floormat, "floor", ((1.2, 0.8, 0.0), (2.4, 1.7, 0.0))),
    "plant": (b_plant, "corner", ((0.35, 0.35, 0.6), (0.6, 0.6, 1.5))),
    "side_table": (b_side_table, "wall", ((0.4, 0.4, 0.5), (0.6, 0.55, 0.7))),
    "lounge_chair": (b_lounge_chair, "free", ((0.7, 0.7, 0.8), (0.85, 0.85, 0.95))),
    "toilet": (b_toilet, "wall", ((0.38, 0.65, 0.78), (0.42, 0.72, 0.82))),
    "bathtub": (b_bathtub, "wall", ((1.5, 0.7, 0.55), (1.8, 0.8, 0.6))),
    "vanity": (b_vanity, "wall", ((0.6, 0.45, 0.85), (1.2, 0.55, 0.9))),
    "otherfurniture": (b_boxlike("otherfurniture", "wood2"), "wall", ((0.5, 0.4, 0.5), (1.0, 0.5, 0.9))),
    # wall-mounted: placement "mount", dims w, depth, h; mount heights in MOUNT_Z
    "picture": (w_picture, "mount", ((0.4, 0.03, 0.3), (1.2, 0.03, 0.8))),
    "whiteboard": (w_whiteboard, "mount", ((1.6, 0.03, 0.9), (3.0, 0.03, 1.2))),
    "mirror": (w_simple("mirror", "mirror"), "mount", ((0.5, 0.02, 0.6), (0.9, 0.02, 1.0))),
    "towel": (w_towel, "mount", ((0.35, 0.03, 0.5), (0.55, 0.03, 0.7))),
    "wall_tv": (w_simple("television", "screen", 0.05), "mount", ((1.0, 0.05, 0.58), (1.4, 0.05, 0.8))),
}
MOUNT_Z = {"picture": (1.3, 1.6), "whiteboard": (0.9, 1.0), "mirror": (1.15, 1.3), "towel": (0.9, 1.1),
           "wall_tv": (1.0, 1.3)}

# room type -> [(kind, min count, max count, probability the family has it)]
ROOMS = {
    "office": [("desk", 1, 3, 1.0), ("chair", 0, 0, 1.0), ("bookshelf", 1, 2, 0.9), ("cabinet", 1, 2, 0.8),
               ("whiteboard", 1, 1, 0.6), ("picture", 1, 2, 0.7), ("boxes", 1, 2, 0.6), ("floorlamp", 1, 1, 0.5),
               ("shelves", 1, 1, 0.5), ("table", 1, 1, 0.4), ("otherfurniture", 1, 1, 0.4), ("floormat", 1, 1, 0.3),
               ("plant", 1, 2, 0.6), ("lounge_chair", 1, 1, 0.3)],
    "bedroom": [("bed", 1, 1, 1.0), ("nightstand", 1, 2, 1.0), ("dresser", 1, 1, 0.8), ("wardrobe", 1, 1, 0.6),
                ("picture", 1, 3, 0.9), ("floormat", 1, 1, 0.6), ("mirror", 1, 1, 0.5), ("desk", 1, 1, 0.4),
                ("chair", 0, 0, 1.0), ("boxes", 1, 1, 0.3), ("floorlamp", 1, 1, 0.4), ("shelves", 1, 1, 0.4),
                ("plant", 1, 1, 0.5), ("lounge_chair", 1, 1, 0.5)],
    "living room": [("sofa", 1, 1, 1.0), ("coffee_table", 1, 1, 0.9), ("tvstand", 1, 1, 0.8), ("armchair", 1, 2, 0.5),
                    ("bookshelf", 1, 1, 0.6), ("picture", 1, 3, 0.9), ("floormat", 1, 1, 0.8), ("floorlamp", 1, 2, 0.8),
                    ("cabinet", 1, 1, 0.4), ("shelves", 1, 1, 0.4), ("otherfurniture", 1, 1, 0.4),
                    ("plant", 1, 2, 0.7), ("side_table", 1, 2, 0.7), ("lounge_chair", 1, 2, 0.7)],
    "kitchen": [("counter", 1, 2, 1.0), ("kitchen_sink", 1, 1, 1.0), ("fridge", 1, 1, 1.0), ("upper_cabinet", 1, 2, 0.8),
                ("table", 1, 1, 0.7), ("chair", 0, 0, 1.0), ("picture", 1, 1, 0.4), ("boxes", 1, 1, 0.3),
                ("shelves", 1, 1, 0.4), ("cabinet", 1, 1, 0.5), ("floormat", 1, 1, 0.3), ("plant", 1, 1, 0.4)],
    "bathroom": [("toilet", 1, 1, 1.0), ("vanity", 1, 1, 1.0), ("mirror", 1, 1, 1.0), ("bathtub", 1, 1, 0.7),
                 ("towel", 1, 2, 0.9), ("floormat", 1, 1, 0.6), ("cabinet", 1, 1, 0.5), ("shelves", 1, 1, 0.5),
                 ("picture", 1, 1, 0.3), ("plant", 1, 1, 0.4)],
    "classroom": [("student_desk", 4, 9, 1.0), ("chair", 0, 0, 1.0), ("whiteboard", 1, 1, 1.0), ("desk", 1, 1, 1.0),
                  ("bookshelf", 1, 2, 0.6), ("cabinet", 1, 2, 0.6), ("picture", 1, 2, 0.5), ("boxes", 1, 1, 0.4),
                  ("plant", 1, 1, 0.4)],
    "dining room": [("dining_table", 1, 1, 1.0), ("chair", 0, 0, 1.0), ("cabinet", 1, 2, 0.8), ("picture", 1, 3, 0.9),
                    ("floorlamp", 1, 1, 0.5), ("otherfurniture", 1, 1, 0.5), ("floormat", 1, 1, 0.4),
                    ("shelves", 1, 1, 0.4), ("plant", 1, 2, 0.6), ("side_table", 1, 1, 0.4)],
    "library": [("bookshelf", 3, 6, 1.0), ("table", 1, 2, 1.0), ("chair", 0, 0, 1.0), ("armchair", 1, 1, 0.5),
                ("floorlamp", 1, 2, 0.6), ("picture", 1, 1, 0.5), ("floormat", 1, 1, 0.5), ("desk", 1, 1, 0.4),
                ("plant", 1, 1, 0.5), ("lounge_chair", 1, 2, 0.5)],
}
# surfaces that carry small props (vases, bottles, bowls, books, paper) and table lamps: kind -> (props, lamp chance)
SURFACES = {"table": (2, 0.1), "dining_table": (3, 0.0), "coffee_table": (2, 0.0), "desk": (2, 0.6),
            "student_desk": (1, 0.0), "nightstand": (1, 0.0), "dresser": (3, 0.5), "counter": (3, 0.1),
            "cabinet": (2, 0.2), "otherfurniture": (2, 0.5), "side_table": (1, 0.8), "shelves": (2, 0.0),
            "vanity": (1, 0.0), "bookshelf": (1, 0.0)}
ROOM_SIZE = {"bathroom": ((2.6, 2.4), (4.0, 3.5)), "kitchen": ((3.2, 3.0), (5.5, 4.5)),
             "classroom": ((5.5, 5.0), (8.0, 7.0)), "library": ((4.5, 4.0), (7.5, 6.5))}


@dataclass
class Family:
    index: int
    room: str
    size: tuple  # W, D, H
    materials: dict
    items: list  # (kind, dims (w, d, h), extra dict)
    wall_key: list  # wall material key per wall
    temp: float = 0.5
    n_lights: int = 2  # ceiling fixtures (dim settings: one)
    window_level: float = 2.0  # daylight through the windows (dim settings: dusk)
    glass: bool = True  # windows glazed (else open: rays escape, invalid pixels)
    skirting: bool = False  # skirting boards along the walls (NYU40 otherstructure)
    pendant: float = 0.0  # how far the ceiling lamps hang below the ceiling (m; 0: flush)
    clutter: float = 0.6  # how many small props stand on the family's surfaces (0..1)


def make_family(seed: int, index: int, room: str) -> Family:
    rng = np.random.default_rng([seed, 7919, index])
    lo, hi = ROOM_SIZE.get(room, ((3.2, 3.0), (6.0, 5.0)))
    W, D = rng.uniform(lo[0], hi[0]), rng.uniform(lo[1], hi[1])
    H = rng.uniform(2.5, 3.2)
    mats = _family_materials(rng, room)
    temp = float(rng.uniform(0.2, 0.8))  # light colour temperature of the family's fixtures (0 warm .. 1 cool)
    items = []
    pic = 0
    for kind, nmin, nmax, p in ROOMS[room]:
        if kind == "chair" or rng.uniform() > p:
            continue
        n = int(rng.integers(nmin, nmax + 1))
        lo_d, hi_d = CATALOGUE[kind][2]
        dims = tuple(float(rng.uniform(a, b)) for a, b in zip(lo_d, hi_d))
        for _ in range(n):
            extra = {}
            if kind == "picture":
                extra["mat"] = f"picture{pic % 3}"
                pic += 1
                dims = tuple(float(rng.uniform(a, b)) for a, b in zip(lo_d, hi_d))
            items.append((kind, dims, extra))
    chair_dims = tuple(float(rng.uniform(a, b)) for a, b in zip(*CATALOGUE["chair"][2]))
    items.append(("chair", chair_dims, {}))  # the family's chair model (the layout decides how many)
    wall_key = ["wall"] * 4
    if rng.uniform() < 0.5:
        wall_key[int(rng.integers(4))] = "wall2"
    return Family(index, room, (W, D, H), mats, items, wall_key, temp, int(rng.integers(1, 4)),
                  float(rng.uniform(2.5, 6.0)), bool(rng.uniform() < 0.85), skirting=bool(rng.uniform() < 0.5),
                  pendant=float(rng.uniform(0.3, 0.9)) if rng.uniform() < 0.5 else 0.0,
                  clutter=float(rng.uniform(0.3, 1.0)))


# =============================================================================================================
# layout of one setting
# =============================================================================================================

def _props_on(it: Item, fam: Family, rng: np.random.Generator) -> list:
    """Small things on the top of `it` (item-local frame): vases, bottles, bowls (otherprop), a stack of books, a
    sheet of paper, sometimes a table lamp. How many follows the family's clutter level."""
    n_max, p_lamp = SURFACES[it.kind]
    top = it.h
    objs = []
    if it.kind not in ("nightstand",) and rng.uniform() < p_lamp:  # nightstands already carry their lamp
        x, y = rng.uniform(-0.35, 0.35) * it.w, rng.uniform(-0.2, 0.2) * it.d
        objs.append(Obj(ID["lamp"], [(_cyl(x, y, top, 0.07, 0.03), "metal"), (_cyl(x, y, top + 0.03, 0.012, 0.22), "metal"),
                                     (_cyl(x, y, top + 0.2, 0.13, 0.18), "shade")]))
    n = int(rng.binomial(n_max, fam.clutter))
    for _ in range(n):
        x, y = rng.uniform(-0.4, 0.4) * it.w, rng.uniform(-0.3, 0.3) * it.d
        kind = rng.choice(["vase", "bottle", "bowl", "books", "paper"], p=[0.35, 0.25, 0.25, 0.1, 0.05])
        mat = f"prop{int(rng.integers(N_PROP_MATERIALS))}"
        if kind == "vase":
            objs.append(Obj(ID["otherprop"], [(_cyl(x, y, top, rng.uniform(0.05, 0.09), rng.uniform(0.15, 0.35), 10), mat)]))
        elif kind == "bottle":
            objs.append(Obj(ID["otherprop"], [(_cyl(x, y, top, 0.035, rng.uniform(0.2, 0.32), 8), mat)]))
        elif kind == "bowl":
            objs.append(Obj(ID["otherprop"], [(_cyl(x, y, top, rng.uniform(0.1, 0.16), 0.07, 12), mat)]))
        elif kind == "books":
            objs.append(Obj(ID["books"], [(_bx(x, y, top, 0.22, 0.16, rng.uniform(0.06, 0.15)), "books")]))
        else:
            objs.append(Obj(ID["paper"], [(_bx(x, y, top, 0.3, 0.22, 0.005), "paper")]))
    return objs


def _rot(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


@dataclass
class Layout:
    W: float
    D: float
    H: float
    items: list  # Item
    rects: list  # (xmin, ymin, xmax, ymax) floor footprints (obstacles)
    lights: list  # (position (3,), rgb (3,))
    ambient: np.ndarray
    window_emission: np.ndarray
    openings: list = field(default_factory=list)  # (wall, s0, s1, z0, z1, kind)


def _wall_frame(w: int, W: float, D: float):
    """(origin (x, y), direction along the wall, inward normal, length) of wall w (0: y=0, 1: x=W, 2: y=D, 3: x=0)."""
    if w == 0:
        return np.array([0.0, 0.0]), np.array([1.0, 0.0]), np.array([0.0, 1.0]), W
    if w == 1:
        return np.array([W, 0.0]), np.array([0.0, 1.0]), np.array([-1.0, 0.0]), D
    if w == 2:
        return np.array([W, D]), np.array([-1.0, 0.0]), np.array([0.0, -1.0]), W
    return np.array([0.0, D]), np.array([0.0, -1.0]), np.array([1.0, 0.0]), D


def _footprint(x, y, yaw, w, d):
    c, s = abs(math.cos(yaw)), abs(math.sin(yaw))
    hx, hy = (w * c + d * s) / 2, (w * s + d * c) / 2
    return (x - hx, y - hy, x + hx, y + hy)


def _overlaps(r, rects, pad=0.05):
    for q in rects:
        if r[0] < q[2] + pad and q[0] < r[2] + pad and r[1] < q[3] + pad and q[1] < r[3] + pad:
            return True
    return False


@dataclass
class _Draft:
    """A layout in progress: the room, the setting's random numbers and what is placed so far."""
    W: float
    D: float
    H: float
    rng: np.random.Generator
    items: list = field(default_factory=list)  # Item
    rects: list = field(default_factory=list)  # floor footprints taken (obstacles)
    high_rects: list = field(default_factory=list)  # footprints of high wall units
    wall_used: dict = field(default_factory=lambda: {w: [] for w in range(4)})  # intervals along each wall taken
    openings: list = field(default_factory=list)  # (wall, s0, s1, z0, z1, kind)
    chair_anchors: list = field(default_factory=list)  # (item, "front1": one chair in front | "around": a table)


def make_layout(fam: Family, seed: int, setting_index: int, dim: bool) -> Layout:
    """One setting of a family, step by step: the family's doors and windows, the furniture (classroom rows of
    desks, then the family's items from the largest footprint down: against a wall, mounted on a wall, or free on
    the floor), small props on the surfaces, chairs at the desks and tables, and the lights. The steps draw from
    one generator of the setting in this order."""
    W, D, H = fam.size
    draft = _Draft(W, D, H, np.random.default_rng([seed, 104729, setting_index]))
    _place_openings(draft, fam, np.random.default_rng([seed, 7919, fam.index, 1]))  # shared by the family
    furniture = [it for it in fam.items if it[0] != "chair"]
    order = sorted(range(len(furniture)), key=lambda i: -furniture[i][1][0] * furniture[i][1][1])
    _place_desk_rows(draft, [furniture[i] for i in order if CATALOGUE[furniture[i][0]][1] == "grid"])
    for i in order:
        _place_furniture(draft, *furniture[i])
    _place_props(draft, fam)
    _place_chairs(draft, [it[1] for it in fam.items if it[0] == "chair"][0])
    lights, ambient, window_emission = _place_lights(draft, fam, seed, dim)
    return Layout(W, D, H, draft.items, draft.rects, lights, ambient, window_emission, draft.openings)


def _place_openings(draft: _Draft, fam: Family, orng: np.random.Generator) -> None:
    """Doors (their swing kept free on the floor) and windows on the walls, from the family's generator `orng`."""
    W, D, H = draft.W, draft.D, draft.H
    n_doors = 1 + int(orng.uniform() < 0.25)
    n_windows = int(orng.integers(0 if fam.room == "bathroom" else 1, 3 if min(W, D) > 3.5 else 2))
    for kind, n in (("door", n_doors), ("window", n_windows)):
        for _ in range(n):
            for _try in range(30):
                w = int(orng.integers(4))
                o, t, nrm, L = _wall_frame(w, W, D)
                ow = orng.uniform(0.8, 0.95) if kind == "door" else orng.uniform(0.9, min(2.2, L - 0.8))
                s0 = orng.uniform(0.3, L - ow - 0.3) if L - ow - 0.6 > 0 else None
                if s0 is None or any(s0 < b + 0.2 and a < s0 + ow + 0.2 for a, b in draft.wall_used[w]):
                    continue
                draft.wall_used[w].append((s0, s0 + ow))
                if kind == "door":
                    z0, z1 = 0.0, 2.05
                    c = o + t * (s0 + ow / 2) + nrm * 0.5
                    draft.rects.append(_footprint(c[0], c[1], w * math.pi / 2, ow + 0.2, 1.0))  # keep the swing free
                else:
                    z0 = orng.uniform(0.8, 1.0)
                    z1 = min(H - 0.25, z0 + orng.uniform(1.1, 1.6))
                draft.openings.append((w, s0, s0 + ow, z0, z1, kind))
                break


def _clear_of_openings(draft: _Draft, w: int, s0: float, s1: float, z0: float, z1: float) -> bool:
    """Whether the span [s0, s1] x [z0, z1] of wall w keeps clear of its doors and windows."""
    for (ww, a, b, oz0, oz1, _k) in draft.openings:
        if ww == w and s0 < b + 0.1 and a < s1 + 0.1 and z0 < oz1 and oz0 < z1:
            return False
    return True


def _place_desk_rows(draft: _Draft, grid_items: list) -> None:
    """Classroom: rows of student desks facing the whiteboard wall (wall 0, -y), a chair in front of each."""
    if not grid_items:
        return
    rng, W, D = draft.rng, draft.W, draft.D
    dims = grid_items[0][1]
    n = len(grid_items)
    cols = max(1, int((W - 1.6) // (dims[0] + 0.5)))
    yaw0 = math.pi  # face wall 0 (-y)
    jitter = rng.uniform(-0.3, 0.3, 2)
    for k in range(n):
        r_, c_ = divmod(k, cols)
        x = 0.8 + dims[0] / 2 + c_ * (dims[0] + 0.5) + jitter[0] + rng.uniform(-0.08, 0.08)
        y = 2.4 + r_ * (dims[1] + 0.9) + jitter[1]
        fp = _footprint(x, y, yaw0, dims[0], dims[1])
        if fp[2] > W - 0.4 or fp[3] > D - 0.6 or fp[0] < 0.3 or _overlaps(fp, draft.rects):
            continue
        it = Item("student_desk", b_desk(dims, {}), *dims, x=x, y=y, yaw=yaw0 + rng.normal(0, 0.04))
        draft.items.append(it)
        draft.rects.append(fp)
        draft.chair_anchors.append((it, "front1"))


def _place_furniture(draft: _Draft, kind: str, dims: tuple, extra: dict) -> None:
    """One of the family's items, placed the way its catalogue entry says (grid items are `_place_desk_rows`')."""
    how = CATALOGUE[kind][1]
    if how in ("wall", "wall_high"):
        it = _place_against_wall(draft, kind, dims, high=(how == "wall_high"))
    elif how == "mount":
        it = _mount_on_wall(draft, kind, dims)
    elif how in ("centre", "free", "corner", "floor"):
        it = _place_on_floor(draft, kind, dims, how)
    else:
        it = None
    if it is not None:
        it.objs = CATALOGUE[kind][0](dims, {}) if kind != "picture" else w_picture(dims, {}, extra["mat"])
        draft.items.append(it)


def _place_against_wall(draft: _Draft, kind: str, dims: tuple, high: bool = False) -> Optional[Item]:
    """A unit standing against a wall (`high`: hung above the floor, 1.3-1.7 m), clear of the doors and windows
    and of the floor footprints (`high`: of the other high units); a desk gets a chair anchor."""
    rng, W, D, H = draft.rng, draft.W, draft.D, draft.H
    w_, d_, h_ = dims
    for _try in range(60):
        w = int(rng.integers(4))
        o, t, nrm, L = _wall_frame(w, W, D)
        if L < w_ + 0.1:
            continue
        s = rng.uniform(w_ / 2 + 0.05, L - w_ / 2 - 0.05)
        z0 = 0.0 if not high else rng.uniform(1.3, min(1.7, H - h_ - 0.1))
        if not _clear_of_openings(draft, w, s - w_ / 2, s + w_ / 2, z0, z0 + h_):
            continue
        c = o + t * s + nrm * (d_ / 2 + 0.02)
        yaw = w * math.pi / 2
        fp = _footprint(c[0], c[1], yaw, w_, d_)
        if _overlaps(fp, draft.high_rects if high else draft.rects):
            continue
        it = Item(kind, [], w_, d_, h_, float(c[0]), float(c[1]), yaw, z0)
        (draft.high_rects if high else draft.rects).append(fp)
        if kind == "desk":
            draft.chair_anchors.append((it, "front1"))
        return it
    return None


def _mount_on_wall(draft: _Draft, kind: str, dims: tuple) -> Optional[Item]:
    """A flat thing on a wall (picture, whiteboard, mirror, towel) at its catalogue height, clear of the doors and
    windows, of other mounted things and of the furniture in front of it."""
    rng, W, D, H = draft.rng, draft.W, draft.D, draft.H
    zlo, zhi = MOUNT_Z[kind]
    for _try in range(60):
        w = int(rng.integers(4))
        o, t, nrm, L = _wall_frame(w, W, D)
        if L < dims[0] + 0.2:
            continue
        s = rng.uniform(dims[0] / 2 + 0.1, L - dims[0] / 2 - 0.1)
        z0 = rng.uniform(zlo, zhi)
        if z0 + dims[2] > H - 0.1 or not _clear_of_openings(draft, w, s - dims[0] / 2, s + dims[0] / 2, z0,
                                                            z0 + dims[2]):
            continue
        if any(a < s + dims[0] / 2 + 0.1 and s - dims[0] / 2 < b + 0.1 for a, b in draft.wall_used[w]):
            continue
        # not behind tall furniture
        c = o + t * s + nrm * 0.05
        fp = _footprint(c[0], c[1], w * math.pi / 2, dims[0], 0.1)
        tall = [_footprint(q.x, q.y, q.yaw, q.w, q.d) for q in draft.items if q.h > z0 - 0.05]
        if _overlaps(fp, tall, pad=0.0) or _overlaps(fp, draft.high_rects, pad=0.0):
            continue
        draft.wall_used[w].append((s - dims[0] / 2, s + dims[0] / 2))
        return Item(kind, [], *dims, x=float(c[0] - nrm[0] * 0.05), y=float(c[1] - nrm[1] * 0.05),
                    yaw=w * math.pi / 2, z0=z0)
    return None


def _place_on_floor(draft: _Draft, kind: str, dims: tuple, how: str) -> Optional[Item]:
    """A free-standing piece: ``centre`` (kept well away from the rest), ``free`` (an armchair facing the room
    centre), ``corner``, or ``floor`` (a floor mat: under the furniture, never on another mat). Tables get chair
    anchors around them."""
    rng, W, D = draft.rng, draft.W, draft.D
    for _try in range(80):
        if how == "corner":
            cx = rng.choice([0.35, W - 0.35])
            cy = rng.choice([0.35, D - 0.35])
            yaw = 0.0
        else:
            m = 0.9 if how == "centre" else 0.6
            cx, cy = rng.uniform(m, W - m), rng.uniform(m, D - m)
            yaw = (rng.integers(4) * math.pi / 2 if how != "free" else rng.uniform(0, 2 * math.pi))
            yaw += rng.normal(0, 0.05)
        fp = _footprint(cx, cy, yaw, dims[0], dims[1])
        if fp[0] < 0.05 or fp[1] < 0.05 or fp[2] > W - 0.05 or fp[3] > D - 0.05:
            continue
        if how != "floor" and _overlaps(fp, draft.rects, pad=0.5 if how == "centre" else 0.15):
            continue
        if how == "floor" and _overlaps(fp, [_footprint(q.x, q.y, q.yaw, q.w, q.d) for q in draft.items
                                             if q.kind == "floormat"]):
            continue
        if how == "free":  # armchair: face the room centre
            yaw = math.atan2(-(W / 2 - cx), (D / 2 - cy))
        it = Item(kind, [], *dims, x=float(cx), y=float(cy), yaw=float(yaw))
        if kind in ("table", "dining_table"):
            draft.chair_anchors.append((it, "around"))
        if how != "floor":
            draft.rects.append(fp)
        return it
    return None


def _place_props(draft: _Draft, fam: Family) -> None:
    """Small props and table lamps on the surfaces (the clutter of real rooms)."""
    for it in draft.items:
        if it.kind in SURFACES:
            it.objs += _props_on(it, fam, draft.rng)


def _place_chairs(draft: _Draft, chair_dims: tuple) -> None:
    """The family's chair in front of each desk and around each table (some seats left empty), where it fits."""
    rng, W, D = draft.rng, draft.W, draft.D
    cw, cd, ch = chair_dims
    for anchor, mode in draft.chair_anchors:
        R = _rot(anchor.yaw)[:2, :2]
        if mode == "front1":
            spots = [(0.0, anchor.d / 2 + 0.15, math.pi)]
        else:
            spots = [(sx * anchor.w / 4, sy * (anchor.d / 2 + 0.2), (0 if sy < 0 else math.pi)) for sx in (-1, 1)
                     for sy in (-1, 1)] + [(sx * (anchor.w / 2 + 0.2), 0.0, sx * -math.pi / 2) for sx in (-1, 1)]
        anchor_fp = _footprint(anchor.x, anchor.y, anchor.yaw, anchor.w, anchor.d)
        for lx, ly, lyaw in spots:
            if mode == "around" and rng.uniform() < 0.3:
                continue
            p = np.array([anchor.x, anchor.y]) + R @ np.array([lx, ly])
            yaw = anchor.yaw + lyaw + rng.normal(0, 0.15)
            p += R @ np.array([rng.normal(0, 0.05), rng.normal(0, 0.05)])
            fp = _footprint(p[0], p[1], yaw, cw, cd)
            if fp[0] < 0.05 or fp[1] < 0.05 or fp[2] > W - 0.05 or fp[3] > D - 0.05:
                continue
            if _overlaps(fp, [r for r in draft.rects if not _overlaps(r, [anchor_fp], -0.01)], pad=0.02):
                continue
            draft.items.append(Item("chair", b_chair(chair_dims, {}), cw, cd, ch, float(p[0]), float(p[1]),
                                    float(yaw)))
            draft.rects.append(fp)


def _place_lights(draft: _Draft, fam: Family, seed: int, dim: bool) -> tuple[list, np.ndarray, np.ndarray]:
    """(lights, ambient, window emission): the family's ceiling fixtures (same positions and colour in every
    setting; their lamps are items), all on in a bright setting, one weak one in a dim setting (and dusk at the
    windows)."""
    W, D, H = draft.W, draft.D, draft.H
    lrng = np.random.default_rng([seed, 7919, fam.index, 2])
    n_lights = 1 if dim else fam.n_lights
    temp = fam.temp
    rgb = np.array([1.0, 0.85 + 0.12 * temp, 0.65 + 0.35 * temp])
    lights = []
    level = draft.rng.uniform(0.9, 1.1) * (0.25 if dim else 1.0)
    for k in range(fam.n_lights):
        pos = np.array([lrng.uniform(0.25, 0.75) * W, lrng.uniform(0.25, 0.75) * D, H - 0.25])
        power = lrng.uniform(4.0, 6.0) * (W * D / 20.0) ** 0.5 / fam.n_lights ** 0.5
        if k < n_lights:
            lights.append((pos, rgb * level * power))
        drop = fam.pendant  # a pendant hangs on a cord into the view; a flush fixture stays at the ceiling
        draft.items.append(Item("ceiling_lamp", [Obj(ID["lamp"], [(_cyl(0, 0, -0.2 - drop, 0.2, 0.14), "shade"),
                                                                (_cyl(0, 0, -0.06 - drop, 0.01, 0.06 + drop),
                                                                 "metal")])],
                                0.3, 0.3, 0.2, float(pos[0]), float(pos[1]), 0.0, H))
    ambient = rgb * (0.12 if not dim else 0.015)
    window_emission = np.array([0.9, 1.0, 1.2]) * (fam.window_level if not dim else 0.04)
    return lights, ambient, window_emission

# =============================================================================================================
# the mesh of a setting
# =============================================================================================================

@dataclass
class SceneMesh:
    vertices: np.ndarray
    faces: np.ndarray
    face_part: np.ndarray  # part index per face
    part_sem: np.ndarray  # NYU40 id per part
    part_inst: np.ndarray  # instance id per part (>= 1)
    part_entity: np.ndarray  # render entity id per part (>= 1)
    part_mat: np.ndarray  # material index per part
    part_inv: np.ndarray  # (P, 4, 4) world -> part-local (for textures)
    materials: list
    instances: list  # (instance id, NYU40 id, name)


def _wall_pieces(L: float, H: float, holes: list) -> list:
    """Rectangles (s0, s1, z0, z1) covering [0, L] x [0, H] minus the given holes."""
    cuts = sorted({0.0, L, *[h[0] for h in holes], *[h[1] for h in holes]})
    out = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        if b - a < 1e-6:
            continue
        mid = (a + b) / 2
        zs = sorted((h[2], h[3]) for h in holes if h[0] <= mid <= h[1])
        z = 0.0
        for z0, z1 in zs:
            if z0 > z:
                out.append((a, b, z, z0))
            z = max(z, z1)
        if z < H:
            out.append((a, b, z, H))
    return out


def build_mesh(fam: Family, lay: Layout, seed: int, setting_index: int) -> SceneMesh:
    rng = np.random.default_rng([seed, 15485863, setting_index])
    mat_names = sorted(fam.materials)
    mat_index = {k: i for i, k in enumerate(mat_names)}
    materials = [fam.materials[k] for k in mat_names]
    glass = Material(GLASS, (0.05, 0.05, 0.05), emission=tuple(lay.window_emission))
    materials.append(glass)
    mat_index["glass"] = len(materials) - 1

    V, F, FP = [], [], []
    psem, pinst, pmat, pinv = [], [], [], []
    instances = []
    nv = 0

    def add_obj(sem: int, parts: list, T: np.ndarray, name: str):
        nonlocal nv
        inst = len(instances) + 1
        instances.append((inst, sem, name))
        inv = np.linalg.inv(T)
        for (v, f), mk in parts:
            vw = v @ T[:3, :3].T + T[:3, 3]
            pidx = len(psem)
            V.append(vw)
            F.append(f + nv)
            FP.append(np.full(len(f), pidx))
            nv += len(v)
            psem.append(sem)
            pinst.append(inst)
            pmat.append(mat_index[mk])
            pinv.append(inv)

    I4 = np.eye(4)
    W, D, H = lay.W, lay.D, lay.H
    # floor, ceiling
    add_obj(ID["floor"], [(_box((-0.2, -0.2, -0.1), (W + 0.2, D + 0.2, 0.0)), "floor")], I4, "floor")
    add_obj(ID["ceiling"], [(_box((-0.2, -0.2, H), (W + 0.2, D + 0.2, H + 0.1)), "ceiling")], I4, "ceiling")
    # walls with holes for doors and windows; local wall frame: x along wall, y into the room, z up
    for w in range(4):
        o, t, nrm, L = _wall_frame(w, W, D)
        T = np.eye(4)
        T[:3, :3] = _rot(w * math.pi / 2)
        T[:2, 3] = o
        holes = [(a, b, z0, z1) for (ww, a, b, z0, z1, k) in lay.openings if ww == w]
        pieces = _wall_pieces(L, H, holes)
        parts = [(_box((s0, -0.12, z0), (s1, 0.0, z1)), fam.wall_key[w]) for s0, s1, z0, z1 in pieces]
        add_obj(ID["wall"], parts, T, f"wall{w}")
        if fam.skirting:  # skirting boards where the wall meets the floor
            add_obj(ID["otherstructure"], [(_box((s0, 0.0, 0.0), (s1, 0.015, 0.1)), "skirting")
                                           for s0, s1, z0, z1 in pieces if z0 == 0.0], T, "skirting")
        for (ww, a, b, z0, z1, k) in lay.openings:
            if ww != w:
                continue
            if k == "door":
                open_ = rng.uniform() < 0.2
                leaf = _box((a + 0.02, -0.06, 0.0), (b - 0.02, -0.02, z1 - 0.02))
                frame = [(_box((a - 0.06, -0.13, 0), (a, 0.02, z1 + 0.06)), "frame"),
                         (_box((b, -0.13, 0), (b + 0.06, 0.02, z1 + 0.06)), "frame"),
                         (_box((a - 0.06, -0.13, z1), (b + 0.06, 0.02, z1 + 0.06)), "frame")]
                if open_:  # swung open into the room
                    leaf = _box((a + 0.02, 0.0, 0.0), (a + 0.06, b - a - 0.04, z1 - 0.02))
                knob = _box((b - 0.12, -0.02, 1.0), (b - 0.08, 0.04, 1.04)) if not open_ else _box((a + 0.06, b - a - 0.2, 1.0), (a + 0.1, b - a - 0.15, 1.04))
                add_obj(ID["door"], [(leaf, "door"), (knob, "metal")] + frame, T, "door")
            else:
                parts = [(_box((a - 0.05, -0.13, z0 - 0.05), (a, 0.02, z1 + 0.05)), "frame"),
                         (_box((b, -0.13, z0 - 0.05), (b + 0.05, 0.02, z1 + 0.05)), "frame"),
                         (_box((a - 0.05, -0.13, z1), (b + 0.05, 0.02, z1 + 0.05)), "frame"),
                         (_box((a - 0.08, -0.13, z0 - 0.05), (b + 0.08, 0.05, z0)), "frame"),
                         (_box(((a + b) / 2 - 0.02, -0.08, z0), ((a + b) / 2 + 0.02, -0.05, z1)), "frame")]
                if fam.glass:  # glass pane (else the opening is left open: invalid pixels beyond)
                    parts.append((_box((a, -0.07, z0), (b, -0.06, z1)), "glass"))
                add_obj(ID["window"], parts, T, "window")
                r = rng.uniform()
                if r < 0.3:  # blinds: slats over the upper part
                    zb = rng.uniform(z0, (z0 + z1) / 2)
                    slats = [(_box((a, 0.03, z), (b, 0.05, z + 0.035)), "frame") for z in np.arange(zb, z1 - 0.03, 0.05)]
                    if slats:
                        add_obj(ID["blinds"], slats, T, "blinds")
                elif r < 0.65:  # curtains on both sides
                    for side in (-1, 1):
                        cw = rng.uniform(0.3, 0.5)
                        x0 = a - 0.15 if side < 0 else b + 0.15 - cw
                        add_obj(ID["curtain"], [(_box((x0, 0.04, 0.1 if z0 > 0.9 else z0 - 0.2), (x0 + cw, 0.1, min(H - 0.05, z1 + 0.25))), "curtain")], T, "curtain")
    # furniture
    for it in lay.items:
        T = np.eye(4)
        T[:3, :3] = _rot(it.yaw)
        T[:3, 3] = (it.x, it.y, it.z0)
        for ob in it.objs:
            name = [k for k, v in ID.items() if v == ob.sem][0]
            add_obj(ob.sem, ob.parts, T, name)
    vertices = np.concatenate(V)
    faces = np.concatenate(F).astype(np.int64)
    npart = len(psem)
    ent = np.arange(1, npart + 1)
    return SceneMesh(vertices, faces, np.concatenate(FP), np.array(psem, np.int16), np.array(pinst, np.int16),
                     ent.astype(np.int16), np.array(pmat), np.stack(pinv), materials, instances)


# =============================================================================================================
# cameras and trajectories
# =============================================================================================================

def look_rotation(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """R_world_from_cam for a camera at `eye` looking at `target` (x right, y up, z backward; world z up)."""
    f = target - eye
    f = f / np.linalg.norm(f)
    x = np.cross(f, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    z = -f
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def make_trajectories(lay: Layout, n_frames: int, seed: int, setting_index: int) -> list:
    """1-2 scenes; each: (eyes (n,3) metres, R (n,3,3), look-at (n,3) metres).

    As in Hypersim, the cameras of a setting dwell on one part of the room: a piece of furniture and what stands
    within 2 m of it. Each scene starts 1.8-4 m away from that part, walks 0.3-1.5 m through free floor, and looks
    at it with a slow wander of its gaze; the height it looks at (0.4-2.1 m) is the scene's own, so some scenes
    show the ceiling and others the floor in front of the furniture.
    """
    rng = np.random.default_rng([seed, 32452843, setting_index])
    n_scenes = 1 if n_frames < 24 else int(rng.integers(1, 3))
    counts = [n_frames // n_scenes + (1 if k < n_frames % n_scenes else 0) for k in range(n_scenes)]
    res = 0.1
    nx, ny = int(lay.W / res), int(lay.D / res)
    gx, gy = (np.arange(nx) + 0.5) * res, (np.arange(ny) + 0.5) * res
    X, Y = np.meshgrid(gx, gy, indexing="ij")
    m = 0.6 if min(lay.W, lay.D) > 3.6 else 0.45
    free = (X > m) & (X < lay.W - m) & (Y > m) & (Y < lay.D - m)
    for r in lay.rects:
        free &= ~((X > r[0] - 0.25) & (X < r[2] + 0.25) & (Y > r[1] - 0.25) & (Y < r[3] + 0.25))
    if not free.any():
        free = (X > 0.4) & (X < lay.W - 0.4) & (Y > 0.4) & (Y < lay.D - 0.4)

    def is_free(p):
        i, j = int(p[0] / res), int(p[1] / res)
        return 0 <= i < nx and 0 <= j < ny and bool(free[i, j])

    # the part of the room the cameras dwell on: a piece of furniture (larger ones more often) and its neighbours;
    # a second scene looks at the same part or, half of the time, at another one
    things = [it for it in lay.items if it.kind not in ("ceiling_lamp", "floormat")]
    weight = np.array([max(0.1, it.w * it.d) for it in things]) ** 0.5

    def part_of_room() -> np.ndarray:
        anchor = things[int(rng.choice(len(things), p=weight / weight.sum()))]
        near = np.array([[it.x, it.y] for it in things if math.hypot(it.x - anchor.x, it.y - anchor.y) < 2.0])
        return 0.5 * (near.mean(axis=0) + np.array([anchor.x, anchor.y]))

    focus = part_of_room()
    scenes = []
    fi, fj = np.nonzero(free)
    for c, n in enumerate(counts):
        if c > 0 and rng.uniform() < 0.5:
            focus = part_of_room()
        dist = np.hypot(gx[fi] - focus[0], gy[fj] - focus[1])
        ring = np.flatnonzero((dist > 1.8) & (dist < 4.0))
        k = int(rng.choice(ring)) if len(ring) else int(np.argmax(dist))
        p = np.array([gx[fi[k]], gy[fj[k]]]) + rng.uniform(-0.04, 0.04, 2)
        # a short walk through free floor, roughly across the line of sight
        sight = math.atan2(focus[1] - p[1], focus[0] - p[0])
        heading = sight + rng.choice([-1, 1]) * math.pi / 2 + rng.normal(0, 0.4)
        step = rng.uniform(0.3, 1.5) / max(1, n - 1)
        pts = [p.copy()]
        for _s in range(n - 1):
            heading += rng.normal(0, 0.1)
            for _t in range(16):
                q = pts[-1] + step * np.array([math.cos(heading), math.sin(heading)])
                if is_free(q):
                    break
                heading += rng.uniform(0.5, 2.5)
            else:
                q = pts[-1]
            pts.append(q)
        pts = np.array(pts)
        h0 = rng.uniform(1.2, 1.7)
        eyes = np.c_[pts, np.clip(h0 + 0.02 * np.sin(np.linspace(0, 3, n) + rng.uniform(0, 6)), 1.0, 1.8)]
        # the gaze: the focus plus a slow wander (two sines per axis) at the scene's own height
        t = np.linspace(0, 1, n)
        wander = np.stack([a * np.sin(2 * math.pi * f * t + ph) for a, f, ph in
                           zip(rng.uniform(0.4, 1.2, 3) * np.array([1, 1, 0.3]), rng.uniform(0.3, 1.0, 3),
                               rng.uniform(0, 2 * math.pi, 3))], axis=1)
        looks = np.c_[np.broadcast_to(focus, (n, 2)), np.full(n, rng.uniform(0.4, 2.1))] + wander
        reach = np.maximum(np.linalg.norm(looks[:, :2] - eyes[:, :2], axis=1), 0.5)  # pitch within -25..+22 degrees
        looks[:, 2] = eyes[:, 2] + np.clip(looks[:, 2] - eyes[:, 2], reach * math.tan(math.radians(-25)),
                                           reach * math.tan(math.radians(22)))
        Rs = np.stack([look_rotation(e, q) for e, q in zip(eyes, looks)])
        scenes.append((eyes, Rs, looks))
    return scenes


def scene_exposures(rng: np.random.Generator, n: int) -> np.ndarray:
    """Exposure of each frame of one scene: one level per scene (x0.7-1.3) and a 2% flicker, steady along the
    trajectory as in Hypersim's renders."""
    return np.exp(rng.uniform(np.log(0.7), np.log(1.3)) + rng.normal(0, 0.02, n))


# =============================================================================================================
# rendering
# =============================================================================================================

class Renderer:
    """Embree (via trimesh) ray caster + shader for one setting's mesh."""

    def __init__(self, mesh: SceneMesh, lay: Layout):
        import trimesh
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        self.mesh = mesh
        self.lay = lay
        self.tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
        self.normals = np.asarray(self.tm.face_normals)
        self.v0 = mesh.vertices[mesh.faces[:, 0]]
        self.rmi = RayMeshIntersector(self.tm, scale_to_box=False)

    def cast(self, origin: np.ndarray, dirs: np.ndarray):
        """Primary rays from one origin: (face index or -1, distance along unit dirs)."""
        o = np.broadcast_to(origin, dirs.shape)
        tri = self.rmi.intersects_first(o, dirs)
        hit = tri >= 0
        t = np.full(len(dirs), np.nan)
        n = self.normals[tri[hit]]
        t[hit] = np.einsum("ij,ij->i", self.v0[tri[hit]] - origin, n) / np.einsum("ij,ij->i", dirs[hit], n)
        return tri, t

    def shade(self, tri: np.ndarray, pts: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """(n, 3) linear radiance of hit points `pts` on faces `tri` seen along `dirs`."""
        m = self.mesh
        part = m.face_part[tri]
        n = self.normals[tri]
        flip = np.einsum("ij,ij->i", n, dirs) > 0
        n[flip] *= -1
        albedo = np.zeros_like(pts)
        emission = np.zeros_like(pts)
        mats = m.part_mat[part]
        ph = np.c_[pts, np.ones(len(pts))]
        for mi in np.unique(mats):
            sel = mats == mi
            inv = m.part_inv[part[sel]]
            local = np.einsum("nij,nj->ni", inv[:, :3, :], ph[sel])
            mat = m.materials[mi]
            albedo[sel] = _albedo(mat, local)
            emission[sel] = mat.emission
        light = np.broadcast_to(self.lay.ambient, pts.shape).copy()
        # cheap ambient occlusion-ish darkening near the floor / ceiling corners
        light *= (0.75 + 0.25 * np.clip(pts[:, 2:3] / 0.5, 0, 1))
        origin = pts + n * 2e-3
        for lp, lrgb in self.lay.lights:
            L = lp - origin
            dist = np.linalg.norm(L, axis=1)
            L /= dist[:, None]
            cos = np.einsum("ij,ij->i", n, L)
            lit = cos > 0
            occl = self.rmi._scene.run(origin[lit], L[lit], dists=(dist[lit] - 0.05).astype(np.float32), query="OCCLUDED")
            vis = np.zeros(len(pts))
            vis[np.nonzero(lit)[0][occl == -1]] = 1.0
            light += lrgb * (vis * cos / np.maximum(dist ** 2, 0.25))[:, None]
        lamp_glow = emission * np.clip(self.lay.lights[0][1].sum() / 6.0, 0.1, 2.0) if len(self.lay.lights) else emission
        glass = np.all(emission > 0.5, axis=1)
        lamp_glow[glass] = emission[glass]
        return albedo * light + lamp_glow


@dataclass
class FrameOut:
    color: np.ndarray
    depth: np.ndarray
    position: np.ndarray  # metres
    semantic: np.ndarray
    instance: np.ndarray
    entity: np.ndarray


def render_frame(r: Renderer, rays_cam: np.ndarray, eye: np.ndarray, R: np.ndarray, exposure: float,
                 timing: Optional[dict] = None) -> FrameOut:
    Hh, Ww = rays_cam.shape[:2]
    t0 = time.perf_counter()
    d = rays_cam.reshape(-1, 3) @ R.T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    tri, t = r.cast(eye, d)
    t1 = time.perf_counter()
    hit = tri >= 0
    pts = eye + d[hit] * t[hit, None]
    col = np.zeros((len(d), 3))
    col[hit] = r.shade(tri[hit], pts, d[hit]) * exposure
    pos = np.full((len(d), 3), np.nan)
    pos[hit] = pts
    sem = np.full(len(d), -1, np.int16)
    inst = np.full(len(d), -1, np.int16)
    ent = np.full(len(d), -1, np.int16)
    part = r.mesh.face_part[tri[hit]]
    sem[hit] = r.mesh.part_sem[part]
    inst[hit] = r.mesh.part_inst[part]
    ent[hit] = r.mesh.part_entity[part]
    depth = np.where(hit, t, np.nan)
    if timing is not None:
        timing["cast"] = timing.get("cast", 0.0) + (t1 - t0)
        timing["shade"] = timing.get("shade", 0.0) + (time.perf_counter() - t1)
    sh = (Hh, Ww)
    return FrameOut(col.reshape(sh + (3,)), depth.reshape(sh), pos.reshape(sh + (3,)), sem.reshape(sh),
                    inst.reshape(sh), ent.reshape(sh))


# =============================================================================================================
# the plan of a dataset and the writing of settings
# =============================================================================================================

def plan(study) -> list[dict]:
    """One dict per setting: name, index, family, room type, split, dim, tilt-shift, meters_per_asset_unit, frames."""
    ds = study.dataset
    n_train, fs = int(ds.train_settings), max(1, int(ds.family_size))
    siblings = int(getattr(ds, "test_siblings", 0))
    settings = []
    # test: one setting per family (the `paper` protocol's places); the first `test_siblings` families also get a
    # second setting (same furniture and materials, another layout: the `siblings` protocol)
    for fam in range(int(ds.test_settings)):
        for member in range(2 if fam < siblings else 1):
            settings.append({"split": "test", "family": fam, "member": member, "frames": int(ds.frames_per_setting)})
    fam = int(ds.test_settings) - 1
    for k in range(n_train):  # training: families of `family_size` settings
        if k % fs == 0:
            fam += 1
        settings.append({"split": "train", "family": fam, "member": k % fs, "frames": int(ds.train_frames_per_setting)})
    total = len(settings)
    if fam + 1 > 1000:  # Hypersim's names hold 3 digits of volume (ai_VVV_NNN): one volume per family
        raise ValueError(f"{study.path or study.name}: dataset: {fam + 1} families of settings, the Hypersim layout "
                         f"names at most 1000 (ai_000 to ai_999); lower train_settings or raise family_size")
    rng = np.random.default_rng([study.seed, 2718])
    n_fam = fam + 1
    room_order = list(rng.permutation(len(ROOM_TYPES)))
    # test families first cycle through the six main room types, then everything cycles through all of them
    main = [i for i in room_order if ROOM_TYPES[i] in ROOM_TYPES[:6]]
    rest = [i for i in room_order if i not in main]
    cycle = main + rest
    fam_room = [ROOM_TYPES[cycle[f % len(cycle)]] for f in range(n_fam)]
    n_dim = int(math.ceil(ds.dim_fraction * total - 1e-9))
    dim_set = set(rng.permutation(total)[:n_dim].tolist())
    n_tilt = min(total, int(ds.tilt_shift_settings))
    tilt_set = set(np.round(np.linspace(0, total, n_tilt, endpoint=False)).astype(int).tolist()) if n_tilt else set()
    for i, s in enumerate(settings):
        s["index"] = i
        s["name"] = f"ai_{(VOLUME0 + s['family']) % 1000:03d}_{s['member'] + 1:03d}"
        s["room_type"] = fam_room[s["family"]]
        s["scene_type"] = SCENE_TYPE_LABEL[s["room_type"]]
        s["dim"] = i in dim_set
        s["tilt_shift"] = i in tilt_set
        s["meters_per_asset_unit"] = 0.0254 if i % 4 == 2 else 0.01
    return settings


def _camera_M(s: dict, width: int, height: int) -> np.ndarray:
    if s["tilt_shift"]:
        return np.array(TILT_SHIFT_M)
    return Camera.canonical(width, height).M


def _camera_proj(s: dict, width: int, height: int) -> np.ndarray:
    if s["tilt_shift"]:
        return np.array(TILT_SHIFT_PROJ).reshape(4, 4)
    tx = math.tan(FOV_X / 2)
    ty = tx * height / width
    return np.array([[1 / tx, 0, 0, 0], [0, 1 / ty, 0, 0], [0, 0, -1.002002002002002, -2.002002002002002],
                     [0, 0, -1.0, 0]])


def _setting_key(s: dict, study) -> dict:
    ds = study.dataset

    return {"version": FORMAT_VERSION, "code": code_version("dataset"), "seed": int(study.seed),
            "width": int(ds.width), "height": int(ds.height), "family_size": int(ds.family_size), "setting": s}


def build_setting(s: dict, seed: int):
    fam = make_family(seed, s["family"], s["room_type"])
    lay = make_layout(fam, seed, s["index"], s["dim"])
    mesh = build_mesh(fam, lay, seed, s["index"])
    scenes = make_trajectories(lay, s["frames"], seed, s["index"])
    r = Renderer(mesh, lay)
    scenes = refine_views(r, scenes)
    return fam, lay, mesh, scenes, r


def refine_views(r: "Renderer", scenes: list, min_depth: float = 1.2) -> list:
    """Turn a frame that faces a wall or furniture at arm's length up to 40 degrees towards open room (probe: 12x9
    rays); the gaze stays on the part of the room the scene dwells on."""
    probe = Camera.canonical(12, 9).rays(9, 12).reshape(-1, 3)
    probe = probe / np.linalg.norm(probe, axis=1, keepdims=True)
    offsets = [0.0] + [sgn * k * math.radians(20) for k in range(1, 3) for sgn in (1, -1)]
    out = []
    for eyes, Rs, looks in scenes:
        Rs, looks = Rs.copy(), looks.copy()
        for i, (e, R) in enumerate(zip(eyes, Rs)):
            f = -R[:, 2]
            yaw0, pitch = math.atan2(f[1], f[0]), math.asin(np.clip(f[2], -1, 1))
            best = (-1.0, None)
            for off in offsets:
                yw = yaw0 + off
                d = np.array([math.cos(yw) * math.cos(pitch), math.sin(yw) * math.cos(pitch), math.sin(pitch)])
                Rc = look_rotation(e, e + d)
                tri, t = r.cast(e, probe @ Rc.T)
                med = float(np.nanmedian(np.where(tri >= 0, t, 10.0)))
                if med > best[0]:
                    best = (med, Rc)
                if med >= min_depth:
                    break
            Rs[i] = best[1]
            looks[i] = e - best[1][:, 2] * max(1.0, min(best[0], 4.0))
        out.append((eyes, Rs, looks))
    return out


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
    _write_csv(detail / "metadata_scene.csv", ["parameter_name", "parameter_value"], [["meters_per_asset_unit", repr(mpau)]])
    _write_csv(detail / "metadata_cameras.csv", ["camera_name"], [[f"cam_{c:02d}"] for c in range(len(scenes))])
    classes: set = set()
    frames = []
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
        exposures = scene_exposures(rng, len(eyes))
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
    write_json(detail / "monolib_synth_setting.json", {"key": study_key, "info": info})
    return info


def _worker(args):
    s, key, width, height, seed, out_dir = args
    final = Path(out_dir) / s["name"]
    tmp = Path(out_dir) / f".tmp_{s['name']}@{socket.gethostname()}@{os.getpid()}"  # whose render it is
    if tmp.exists():
        shutil.rmtree(tmp)
    try:
        info = render_setting(s, key, width, height, seed, tmp)
        _set_aside(final)
        os.replace(tmp, final)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return info


def _abandoned(tmp: Path) -> bool:
    """A render folder ``.tmp_<setting>@<host>@<pid>`` whose process is gone (on this host: no such pid); one of
    another host, or of a living process, belongs to another run and stays."""
    parts = tmp.name.split("@")
    if len(parts) != 3 or not parts[2].isdigit():
        return True  # the layout of before (.tmp_<setting>_<pid>): written by a run of older code, long ended
    host, pid = parts[1], int(parts[2])
    if host != socket.gethostname():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:  # a living process of another user
        return False
    return False


def _rendered_key(final: Path):
    """The key a complete setting folder was rendered with (None: no readable marker, an unfinished render)."""
    try:
        return json.loads((final / "_detail" / "monolib_synth_setting.json").read_text()).get("key")
    except (OSError, ValueError):
        return None


def _aside(final: Path, key) -> Path:
    """Where a setting rendered with another key waits: ``<dataset>/.aside/<setting>@<hash of its key>/``."""
    digest = hashlib.sha256(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()[:12]
    return final.parent / ".aside" / f"{final.name}@{digest}"


def _set_aside(final: Path) -> None:
    """Make room for a new render of `final`: a complete setting of another key (another study file rendering
    into this folder) is moved aside, never deleted; an unfinished one (a killed render's) is removed."""
    if final.exists():
        key = _rendered_key(final)
        move_aside(final, None if key is None else _aside(final, key))


def _restore(final: Path, key: dict) -> Optional[dict]:
    """A setting of `key` rendered earlier and set aside by another key's render: moved back (the other moved aside
    in turn). Returns its info, or None when there is none."""
    mine = _aside(final, json.loads(json.dumps(key)))
    info = _finished(mine, key) if mine.is_dir() else None
    if info is None:
        return None
    _set_aside(final)
    os.replace(mine, final)
    return info


def _finished(final: Path, key: dict) -> Optional[dict]:
    marker = final / "_detail" / "monolib_synth_setting.json"
    if not marker.is_file():
        return None
    try:
        data = json.loads(marker.read_text())
    except (OSError, ValueError):
        return None
    return data.get("info") if data.get("key") == json.loads(json.dumps(key)) else None


def render_dataset(study, out_dir, progress: bool = True) -> Path:
    """Render every setting of `study` into `out_dir` in Hypersim's layout (resumable, deterministic)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    ds = study.dataset
    W, H = int(ds.width), int(ds.height)
    settings = plan(study)
    for p in out_dir.glob(".tmp_ai_*"):  # leftovers of a killed run: never a render another process is writing
        if _abandoned(p):
            shutil.rmtree(p, ignore_errors=True)
    wanted = {s["name"] for s in settings}
    stale = [p for p in out_dir.glob("ai_9[0-9][0-9]_[0-9][0-9][0-9]") if p.is_dir() and p.name not in wanted
             and (p / "_detail" / "monolib_synth_setting.json").is_file()]
    if stale:  # settings of another study file rendered here (a larger one of the same name): kept, and left out
        # of this dataset by its split file (metadata_images_split_scene_v1.csv lists this study's settings only)
        print(f"monolib.data.synth: {len(stale)} synthetic settings in {out_dir} are not in this study (kept; not read)",
              flush=True)
    infos: dict[str, dict] = {}
    todo = []
    for s in settings:
        key = _setting_key(s, study)
        info = _finished(out_dir / s["name"], key) or _restore(out_dir / s["name"], key)
        if info is not None:
            infos[s["name"]] = info
        else:
            todo.append((s, key, W, H, int(study.seed), str(out_dir)))
    print(f"monolib.data.synth: {len(settings)} settings in {out_dir}: {len(infos)} already complete (skipped), "
          f"{len(todo)} to render", flush=True)
    workers = max(1, min(int(ds.workers), len(todo)))
    t0 = time.perf_counter()
    bar = tqdm(total=len(todo), desc="render settings", unit="setting", disable=not progress)
    if todo:
        if workers == 1:
            for a in todo:
                info = _worker(a)
                infos[info["name"]] = info
                bar.update(1)
        else:
            ctx = mp.get_context("fork" if "fork" in mp.get_all_start_methods() else "spawn")
            with ctx.Pool(workers, initializer=_init_worker) as pool:
                for info in pool.imap_unordered(_worker, todo):
                    infos[info["name"]] = info
                    bar.update(1)
    bar.close()
    elapsed = time.perf_counter() - t0
    _write_root(out_dir, study, settings, infos, W, H)
    if todo:
        nframes = sum(a[0]["frames"] for a in todo)
        print(f"monolib.data.synth: rendered {len(todo)} settings ({nframes} frames) in {elapsed:.1f} s", flush=True)
    return out_dir


def _init_worker():
    try:
        import threadpoolctl  # noqa: F401

        threadpoolctl.threadpool_limits(1)
    except Exception:
        pass


def _write_root(out_dir: Path, study, settings: list, infos: dict, W: int, H: int) -> None:
    split_rows, cam_rows, traj_rows = [], [], []
    for s in settings:
        info = infos[s["name"]]
        for cname, n in zip(info["scenes"], info["frames_per_scene"]):
            for i in range(n):
                split_rows.append([s["name"], cname, i, "True", "", s["split"]])
            traj_rows.append([f"{s['name']}_{cname}", "", "", "", "", "", "", s["scene_type"], "monolib.data.synth", ""])
        row = {c: "" for c in CAMERA_COLUMNS}
        M, P = _camera_M(s, W, H), _camera_proj(s, W, H)
        row.update({"scene_name": s["name"], "settings_output_img_height": repr(float(H)),
                    "settings_output_img_width": repr(float(W)),
                    "settings_units_info_meters_scale": repr(float(s["meters_per_asset_unit"])),
                    "use_camera_physical": str(bool(s["tilt_shift"])), "settings_camera_fov": repr(FOV_X)})
        for a in range(3):
            for b in range(3):
                row[f"M_cam_from_uv_{a}{b}"] = repr(float(M[a, b]))
        for a in range(4):
            for b in range(4):
                row[f"M_proj_{a}{b}"] = repr(float(P[a, b]))
        cam_rows.append([row[c] for c in CAMERA_COLUMNS])
    _write_csv(out_dir / "metadata_images_split_scene_v1.csv", SPLIT_COLUMNS, split_rows)
    _write_csv(out_dir / "metadata_camera_parameters.csv", CAMERA_COLUMNS, cam_rows)
    _write_csv(out_dir / "metadata_camera_trajectories.csv", TRAJECTORY_COLUMNS, traj_rows)
    ds = study.dataset
    meta = {"generator": "monolib.data.synth", "version": FORMAT_VERSION, "seed": int(study.seed),
            "dataset": {k: getattr(ds, k) for k in ("width", "height", "train_settings", "test_settings",
                                                    "test_siblings", "family_size", "frames_per_setting", "train_frames_per_setting",
                                                    "dim_fraction", "tilt_shift_settings")},
            "settings": [{k: infos[s["name"]].get(k) for k in
                          ("name", "index", "family", "member", "room_type", "scene_type", "split", "dim",
                           "tilt_shift", "meters_per_asset_unit", "frames", "scenes", "frames_per_scene", "classes",
                           "room_size_m", "num_lights")} for s in settings]}
    write_json(out_dir / "monolib_synth.json", meta)


# =============================================================================================================
# benchmark
# =============================================================================================================

def benchmark(width: int = 256, height: int = 192, frames: int = 20, seed: int = 0) -> dict:
    """Render one setting's frames into a temporary folder; print and return frames per second by stage."""
    import tempfile
    from types import SimpleNamespace

    ds = SimpleNamespace(width=width, height=height, train_settings=0, test_settings=1, test_siblings=0, family_size=1,
                         frames_per_setting=frames, train_frames_per_setting=frames, dim_fraction=0.0,
                         tilt_shift_settings=0, workers=1)
    study = SimpleNamespace(seed=seed, dataset=ds)
    s = plan(study)[0]
    timing: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        render_setting(s, _setting_key(s, study), width, height, seed, Path(tmp) / s["name"], timing)
        total = time.perf_counter() - t0
    n = timing.get("frames", 0)
    res = {"width": width, "height": height, "frames": n, "total_s": total, "build_s": timing.get("build", 0.0),
           "cast_ms_per_frame": 1000 * timing.get("cast", 0.0) / n, "shade_ms_per_frame": 1000 * timing.get("shade", 0.0) / n,
           "write_ms_per_frame": 1000 * timing.get("write", 0.0) / n, "fps": n / total}
    print(f"monolib.data.synth benchmark {width}x{height}, {n} frames: {res['fps']:.2f} frames/s overall; per frame: "
          f"cast {res['cast_ms_per_frame']:.1f} ms, shade (+shadows) {res['shade_ms_per_frame']:.1f} ms, "
          f"write {res['write_ms_per_frame']:.1f} ms; scene build {res['build_s']:.2f} s")
    return res


if __name__ == "__main__":
    benchmark()
