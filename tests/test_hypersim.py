"""The reader on Hypersim-layout files written here, against values derived by hand."""
from pathlib import Path

import numpy as np
import pytest
from hypersim_files import AI_037_002_M, CAMERA_CENTRE_M, MPAU, WALL_AHEAD_M, write_setting

from monolib.data.hypersim import Camera, HypersimDataset, tonemap
from monolib.io import DataFileError, write_h5

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "hypersim"


@pytest.fixture
def tilt_root(tmp_path):
    return write_setting(tmp_path)


def test_index_lists_settings_scenes_frames_without_opening_images(tilt_root):
    (tilt_root / "ai_037_002" / "images" / "scene_cam_00_geometry_hdf5"
     / "frame.0001.semantic.hdf5").write_bytes(b"junk")
    ds = HypersimDataset(tilt_root)
    assert ds.settings() == ["ai_037_002"]
    assert ds.settings("test") == ["ai_037_002"] and ds.settings("train") == []
    assert ds.scenes("ai_037_002") == ["cam_00"]
    assert ds.frame_ids("ai_037_002", "cam_00") == [0, 1]
    with pytest.raises(DataFileError, match="frame.0001.semantic.hdf5"):
        ds.frame("ai_037_002", "cam_00", 1).semantic


def test_folders_that_are_not_setting_names_are_named_in_a_warning(tilt_root):
    """A folder like ai_1000_001 (4 digits of volume) is not a Hypersim setting: it is left out, and said to be."""
    import shutil

    shutil.copytree(tilt_root / "ai_037_002", tilt_root / "ai_1037_002")
    with pytest.warns(UserWarning, match=r"1 folders that are not Hypersim setting names.*ai_1037_002"):
        ds = HypersimDataset(tilt_root)
    assert ds.settings() == ["ai_037_002"]


def test_tilt_shift_planar_depth_of_a_wall_is_its_distance(tilt_root):
    ds = HypersimDataset(tilt_root)
    f = ds.frame("ai_037_002", "cam_00", 0)
    assert not f.camera.is_canonical
    wall = f.semantic == 1
    assert wall.sum() > 100
    # every wall pixel lies on the plane 4 m in front of the camera: its planar depth is 4 m, whatever the ray
    np.testing.assert_allclose(f.depth[wall], WALL_AHEAD_M, atol=0.01)


def test_tilt_shift_world_points_put_the_floor_at_zero(tilt_root):
    ds = HypersimDataset(tilt_root)
    f = ds.frame("ai_037_002", "cam_00", 0)
    floor = f.semantic == 2
    assert floor.sum() > 100
    world = f.points_world()
    np.testing.assert_allclose(world[floor][:, 2], 0.0, atol=0.03)
    np.testing.assert_allclose(world[f.semantic == 1][:, 1], CAMERA_CENTRE_M[1] + WALL_AHEAD_M, atol=0.03)
    # camera frame: the camera looks along -z, so points in front have negative z equal to minus planar depth
    cam = f.points_cam()
    np.testing.assert_allclose(-cam[..., 2], f.depth, rtol=1e-5)


def test_canonical_matrix_misplaces_a_tilt_shift_floor(tmp_path):
    root = write_setting(tmp_path, camera_row=False)
    ds = HypersimDataset(root)
    with pytest.warns(UserWarning, match="ai_037_002.*canonical"):
        cam = ds.camera("ai_037_002")
    assert cam.is_canonical
    f = ds.frame("ai_037_002", "cam_00", 0)
    floor = f.semantic == 2
    assert np.abs(np.median(f.points_world()[floor][:, 2])) > 0.05  # why the per-scene matrix is required


def test_units_fall_back_to_the_camera_csv(tmp_path):
    root = write_setting(tmp_path, metadata_scene=False)
    ds = HypersimDataset(root)
    assert ds.meters_per_asset_unit("ai_037_002") == pytest.approx(MPAU)
    f = ds.frame("ai_037_002", "cam_00", 0)
    np.testing.assert_allclose(f.points_world()[f.semantic == 2][:, 2], 0.0, atol=0.03)


def test_missing_colour_gives_none_and_missing_depth_names_the_file(tmp_path):
    root = write_setting(tmp_path, with_color=False)
    f = HypersimDataset(root).frame("ai_037_002", "cam_00", 0)
    assert f.rgb is None
    f.files["depth_meters"].unlink()
    with pytest.raises(DataFileError, match="depth_meters.hdf5"):
        f.depth


def test_nan_depth_stays_nan(tmp_path):
    root = write_setting(tmp_path)
    f = HypersimDataset(root).frame("ai_037_002", "cam_00", 0)
    d = np.full((48, 64), np.nan, np.float16)
    write_h5(f.files["depth_meters"], d)
    assert np.isnan(f.depth).all() and np.isnan(f.points_world()).all()


def test_canonical_planar_depth_matches_niklaus_formula():
    H, W = 768, 1024
    cam = Camera.canonical()
    dist = np.full((H, W), 5.0, np.float32)
    f = 886.81
    xp, yp = np.meshgrid(np.arange(W) + 0.5 - W / 2, np.arange(H) + 0.5 - H / 2)
    np.testing.assert_allclose(cam.planar_from_euclidean(dist), 5.0 * f / np.sqrt(xp**2 + yp**2 + f**2), rtol=1e-4)


def test_tonemap_follows_hypersim():
    rng = np.random.default_rng(0)
    color = rng.uniform(0, 3, (20, 30, 3)).astype(np.float32)
    valid = np.ones((20, 30), bool)
    valid[:5] = False
    y = 0.3 * color[..., 0] + 0.59 * color[..., 1] + 0.11 * color[..., 2]
    scale = 0.8 ** 2.2 / np.percentile(y[valid], 90)
    expected = np.clip((scale * color) ** (1 / 2.2), 0, 1)
    np.testing.assert_allclose(tonemap(color, valid) / 255.0, expected, atol=0.5 / 255 + 1e-6)
    assert (tonemap(np.zeros((4, 4, 3)), np.zeros((4, 4), bool)) == 0).all()


@pytest.mark.skipif(not (SHARED / "metadata_camera_parameters.csv").exists(), reason="shared Hypersim metadata absent")
def test_real_camera_csv_row_of_ai_037_002(tmp_path):
    ds = HypersimDataset(tmp_path, metadata_dir=SHARED)
    cam = ds._cameras["ai_037_002"]
    np.testing.assert_allclose(cam.M, np.array(AI_037_002_M), rtol=1e-12)
    assert cam.meters_per_asset_unit == pytest.approx(MPAU)
    assert ds._split.get("ai_037_002") in ("train", "val", "test")
