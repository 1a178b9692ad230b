"""Write Hypersim-layout files for tests: a camera looking along world +y at a wall 4 m ahead over a floor."""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from monolib.data.hypersim import CAMERA_CSV, SPLIT_CSV, Camera
from monolib.io import write_h5

# ai_037_002's row of metadata_camera_parameters.csv (a tilt-shift camera); numbers are facts
AI_037_002_M = ((0.579607251426182, 0.0, -0.06955286861651404),
                (0.0, 0.4346865334657201, 0.09273312506660672),
                (-0.0, 0.004054126980668954, -1.003909173803896))
MPAU = 0.009999999776482582  # its settings_units_info_meters_scale (centimetres)
CAMERA_CENTRE_M = np.array([1.0, 2.0, 0.8])
WALL_AHEAD_M = 4.0
# camera x -> world x, camera y (up) -> world z, camera z (backward) -> world -y: the camera looks along +y
R_WORLD_FROM_CAM = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def render_box(M, height: int, width: int):
    """Euclidean distance (m), world points (m) and labels (1 wall, 2 floor) of the wall-and-floor world."""
    r = Camera(M).rays(height, width)
    d = r / np.linalg.norm(r, axis=-1, keepdims=True)
    world_dir = d @ R_WORLD_FROM_CAM.T
    with np.errstate(divide="ignore"):
        t_wall = np.where(world_dir[..., 1] > 0, WALL_AHEAD_M / world_dir[..., 1], np.inf)
        t_floor = np.where(world_dir[..., 2] < 0, CAMERA_CENTRE_M[2] / -world_dir[..., 2], np.inf)
    t = np.minimum(t_wall, t_floor)
    labels = np.where(t_floor < t_wall, 2, 1).astype(np.int16)
    points = CAMERA_CENTRE_M + t[..., None] * world_dir
    return t, points, labels


def write_setting(root: Path, setting: str = "ai_037_002", M=AI_037_002_M, height: int = 48, width: int = 64,
                  frames: int = 2, camera_row: bool = True, metadata_scene: bool = True, split: str = "test",
                  with_color: bool = True) -> Path:
    root = Path(root)
    t, points, labels = render_box(M, height, width)
    labels[:4, :4] = -1  # an unlabelled corner
    geo = root / setting / "images" / "scene_cam_00_geometry_hdf5"
    fin = root / setting / "images" / "scene_cam_00_final_hdf5"
    for i in range(frames):
        write_h5(geo / f"frame.{i:04d}.depth_meters.hdf5", t.astype(np.float16))
        write_h5(geo / f"frame.{i:04d}.position.hdf5", (points / MPAU).astype(np.float16))
        write_h5(geo / f"frame.{i:04d}.semantic.hdf5", labels)
        write_h5(geo / f"frame.{i:04d}.render_entity_id.hdf5", np.where(labels > 0, labels, 1).astype(np.int16))
        if with_color:
            color = np.stack([labels * 0.2, labels * 0.1, np.full(labels.shape, 0.3)], -1).astype(np.float16)
            write_h5(fin / f"frame.{i:04d}.color.hdf5", color)
    cam = root / setting / "_detail" / "cam_00"
    write_h5(cam / "camera_keyframe_positions.hdf5", np.tile(CAMERA_CENTRE_M / MPAU, (frames, 1)))
    write_h5(cam / "camera_keyframe_orientations.hdf5", np.tile(R_WORLD_FROM_CAM, (frames, 1, 1)))
    if metadata_scene:
        (root / setting / "_detail" / "metadata_scene.csv").write_text(
            f"parameter_name,parameter_value\nmeters_per_asset_unit,{MPAU}\n")
    if camera_row:
        path = root / CAMERA_CSV
        new = not path.exists()
        with open(path, "a", newline="") as f:
            w = csv.writer(f)
            if new:
                w.writerow(["scene_name", "settings_output_img_height", "settings_output_img_width",
                            "settings_units_info_meters_scale"]
                           + [f"M_cam_from_uv_{i}{j}" for i in range(3) for j in range(3)])
            w.writerow([setting, "768.0", "1024.0", MPAU] + [M[i][j] for i in range(3) for j in range(3)])
    path = root / SPLIT_CSV
    new = not path.exists()
    with open(path, "a", newline="") as f:
        w = csv.writer(f)
        if new:
            w.writerow(["scene_name", "camera_name", "frame_id", "included_in_public_release", "exclude_reason",
                        "split_partition_name"])
        for i in range(frames):
            w.writerow([setting, "cam_00", i, "True", "", split])
    return root
