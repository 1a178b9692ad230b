"""The procedural mini-Hypersim (monolib.data.synth), checked against the format spec with h5py alone.

The layout checked is Hypersim's: the scene folders, `_detail` metadata, the camera files and the frames' HDF5 and
preview files, as `monolib.data.hypersim` reads them from a real download.
"""
import csv
import json
import math
import shutil
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

from monolib import params
from monolib.data import synth


def h5(path: Path) -> np.ndarray:
    with h5py.File(path, "r") as f:
        assert list(f.keys()) == ["dataset"], path
        assert dict(f["dataset"].attrs) == {}, path
        return f["dataset"][()]


def mpau_of(setting: Path) -> float:
    with open(setting / "_detail" / "metadata_scene.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert rows[0]["parameter_name"] == "meters_per_asset_unit"
    return float(rows[0]["parameter_value"])


def split_rows(root: Path) -> list[dict]:
    with open(root / "metadata_images_split_scene_v1.csv", newline="") as f:
        return list(csv.DictReader(f))


def frames_on_disk(root: Path):
    for s in sorted(root.glob("ai_*")):
        for d in sorted((s / "images").glob("scene_cam_*_final_hdf5")):
            cam = d.name[len("scene_"):-len("_final_hdf5")]
            for p in sorted(d.glob("frame.*.color.hdf5")):
                yield s, cam, int(p.name.split(".")[1])


def files(setting: Path, cam: str, i: int) -> dict:
    g = setting / "images" / f"scene_{cam}_geometry_hdf5"
    stem = f"frame.{i:04d}"
    out = {k: g / f"{stem}.{k}.hdf5" for k in ("depth_meters", "position", "semantic", "semantic_instance",
                                               "render_entity_id")}
    out["color"] = setting / "images" / f"scene_{cam}_final_hdf5" / f"{stem}.color.hdf5"
    out["tonemap"] = setting / "images" / f"scene_{cam}_final_preview" / f"{stem}.tonemap.jpg"
    return out


@pytest.fixture(scope="module")
def smoke_params():
    return params.load_study("smoke")


def _tiny_study():
    from types import SimpleNamespace

    ds = SimpleNamespace(width=64, height=48, train_settings=0, test_settings=1, test_siblings=0, family_size=1,
                         frames_per_setting=4, train_frames_per_setting=4, dim_fraction=0.0, tilt_shift_settings=0,
                         base_train_settings=None, coplanar="exact", workers=1)
    return SimpleNamespace(seed=3, dataset=ds)


def test_plan_families_splits_and_names(smoke_params):
    q = params.load_study("quick")
    for study in (smoke_params, q):
        plan = synth.plan(study)
        ds = study.dataset
        n_test = ds.test_settings + ds.test_siblings
        assert len(plan) == n_test + ds.train_settings
        assert all(s["split"] == "test" for s in plan[:n_test])
        fam_split = {}
        for s in plan:
            assert s["name"] == f"ai_{900 + s['family']:03d}_{s['member'] + 1:03d}"
            assert fam_split.setdefault(s["family"], s["split"]) == s["split"]  # families never split
        assert sum(s["dim"] for s in plan) >= ds.dim_fraction * len(plan)
        assert sum(s["tilt_shift"] for s in plan) >= ds.tilt_shift_settings
        assert {s["meters_per_asset_unit"] for s in plan} == {0.01, 0.0254}
        # test: `test_settings` families, the first `test_siblings` of them with exactly two settings
        test = [s for s in plan if s["split"] == "test"]
        members = {}
        for s in test:
            members.setdefault(s["family"], []).append(s["member"])
        assert len(members) == ds.test_settings
        assert [len(m) for m in members.values()] == ([2] * ds.test_siblings
                                                      + [1] * (ds.test_settings - ds.test_siblings))
        train = [s for s in plan if s["split"] == "train"]
        sizes = {}
        for s in train:
            sizes[s["family"]] = sizes.get(s["family"], 0) + 1
        assert max(sizes.values()) == ds.family_size  # training settings have siblings too


def test_siblings_share_materials_and_catalogue_not_layout(smoke_params):
    plan = synth.plan(smoke_params)
    a, b = [s for s in plan if s["split"] == "test" and s["family"] == 0]
    fa, fb = synth.make_family(0, a["family"], a["room_type"]), synth.make_family(0, b["family"], b["room_type"])
    assert fa.materials == fb.materials and fa.items == fb.items
    la, lb = synth.make_layout(fa, 0, a["index"], a["dim"]), synth.make_layout(fb, 0, b["index"], b["dim"])
    assert [(i.x, i.y) for i in la.items] != [(i.x, i.y) for i in lb.items]
    other = [s for s in plan if s["family"] != 0][0]
    fo = synth.make_family(0, other["family"], other["room_type"])
    assert fo.materials["wall"] != fa.materials["wall"] and fo.materials["floor"] != fa.materials["floor"]


def test_scene_exposure_is_steady_along_a_trajectory():
    e = synth.scene_exposures(np.random.default_rng(0), 40)
    assert 0.7 * 0.9 < e.min() and e.max() < 1.3 * 1.1
    assert np.std(np.log(e)) < 0.05  # one level per scene, a small flicker


def test_files_dtypes_shapes_and_labels(smoke_dataset, smoke_params):
    H, W = smoke_params.dataset.height, smoke_params.dataset.width
    n = 0
    for s, cam, i in frames_on_disk(smoke_dataset):
        f = files(s, cam, i)
        color = h5(f["color"])
        assert color.dtype == np.float16 and color.shape == (H, W, 3)
        assert np.isfinite(color).all() and (color >= 0).all()
        depth, pos = h5(f["depth_meters"]), h5(f["position"])
        assert depth.dtype == np.float16 and depth.shape == (H, W)
        assert pos.dtype == np.float16 and pos.shape == (H, W, 3)
        sem, inst, ent = h5(f["semantic"]), h5(f["semantic_instance"]), h5(f["render_entity_id"])
        for a in (sem, inst, ent):
            assert a.dtype == np.int16 and a.shape == (H, W)
            assert not (a == 0).any()
        assert set(np.unique(sem)) <= {-1, *range(1, 41)}
        assert (inst >= -1).all() and (ent >= -1).all()
        invalid = ent == -1  # the sky through a window: no geometry, no depth, the sky's radiance
        unlabelled = sem == -1  # the sky and the outside (ground, facades, trees: geometry without a label)
        assert (unlabelled >= invalid).all() and ((inst == -1) == unlabelled).all()
        assert (np.isnan(depth) == invalid).all()
        assert (color[invalid] > 0).all()
        assert f["tonemap"].is_file()
        jpg = cv2.imread(str(f["tonemap"]))
        assert jpg is not None and jpg.shape == (H, W, 3)
        n += 1
    assert n == sum(s["frames"] for s in synth.plan(smoke_params))


def test_depth_is_euclidean_distance_of_position_in_asset_units(smoke_dataset):
    for s, cam, i in frames_on_disk(smoke_dataset):
        mpau = mpau_of(s)
        assert mpau in (0.01, 0.0254)
        c = h5(s / "_detail" / cam / "camera_keyframe_positions.hdf5")
        assert c.dtype == np.float64 and c.ndim == 2 and c.shape[1] == 3
        f = files(s, cam, i)
        depth = h5(f["depth_meters"]).astype(np.float32)
        pos = h5(f["position"]).astype(np.float64)
        assert (np.isnan(depth) == np.isnan(pos).any(-1)).all()
        expect = mpau * np.linalg.norm(pos - c[i], axis=-1)
        ok = ~np.isnan(depth)
        # float16: position step <= 0.5 asset units, depth step <= 0.0078 m below 16 m
        tol = 0.01 + 2e-3 * expect[ok] + mpau * 0.5
        assert (np.abs(depth[ok] - expect[ok]) <= tol).all(), (s.name, cam, i)


def test_camera_poses(smoke_dataset):
    for s in sorted(smoke_dataset.glob("ai_*")):
        mpau = mpau_of(s)
        with open(s / "_detail" / "metadata_cameras.csv", newline="") as f:
            cams = [r["camera_name"] for r in csv.DictReader(f)]
        assert 1 <= len(cams) <= 3
        for cam in cams:
            d = s / "_detail" / cam
            R = h5(d / "camera_keyframe_orientations.hdf5")
            t = h5(d / "camera_keyframe_positions.hdf5")
            idx = h5(d / "camera_keyframe_frame_indices.hdf5")
            look = h5(d / "camera_keyframe_look_at_positions.hdf5")
            assert R.dtype == np.float64 and R.shape == (len(t), 3, 3) and look.shape == t.shape
            assert list(idx) == list(range(len(t)))
            np.testing.assert_allclose(R.transpose(0, 2, 1) @ R, np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
            np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)
            assert (R[:, 2, 1] > 0.857).all()  # camera y (up) is about world +z: pitch within 30 degrees, no roll
            assert (R[:, 2, 0] == pytest.approx(0.0, abs=1e-9))  # camera x stays horizontal
            h = t[:, 2] * mpau
            assert ((h >= 1.09) & (h <= 1.91)).all()  # Hypersim's walk: standing height, +-0.25 m a step
            fwd = -R[:, :, 2]
            to_look = look - t
            assert (np.einsum("ij,ij->i", fwd, to_look / np.linalg.norm(to_look, axis=1, keepdims=True)) > 0.999).all()
            frames = sorted((s / "images" / f"scene_{cam}_final_hdf5").glob("frame.*.color.hdf5"))
            assert len(frames) == len(t)


def test_split_csv_matches_frames_and_metadata(smoke_dataset, smoke_params):
    rows = split_rows(smoke_dataset)
    assert list(rows[0].keys()) == synth.SPLIT_COLUMNS
    on_disk = {(s.name, cam, i) for s, cam, i in frames_on_disk(smoke_dataset)}
    assert {(r["scene_name"], r["camera_name"], int(r["frame_id"])) for r in rows} == on_disk
    assert len(rows) == len(on_disk)
    assert {r["included_in_public_release"] for r in rows} == {"True"}
    split = {}
    for r in rows:
        assert split.setdefault(r["scene_name"], r["split_partition_name"]) == r["split_partition_name"]
    ds = smoke_params.dataset
    assert sorted(split.values()).count("test") == ds.test_settings + ds.test_siblings
    assert sorted(split.values()).count("train") == ds.train_settings
    for s in set(split):
        n = sum(1 for r in rows if r["scene_name"] == s)
        assert n == (ds.frames_per_setting if split[s] == "test" else ds.train_frames_per_setting)
    fam = {}
    for s, p in split.items():
        assert fam.setdefault(s[:6], p) == p  # a family (volume) is never split across train and test

    with open(smoke_dataset / "metadata_camera_parameters.csv", newline="") as f:
        cam_rows = list(csv.DictReader(f))
    assert {r["scene_name"] for r in cam_rows} == set(split)
    assert "M_cam_from_uv_22" in cam_rows[0] and "M_proj_33" in cam_rows[0]
    for r in cam_rows:
        assert float(r["settings_output_img_width"]) == ds.width and "." in r["settings_output_img_width"]
        assert float(r["settings_units_info_meters_scale"]) == mpau_of(smoke_dataset / r["scene_name"])
    tilt = [r for r in cam_rows if float(r["M_cam_from_uv_02"]) != 0.0]
    assert len(tilt) >= ds.tilt_shift_settings
    assert float(tilt[0]["M_cam_from_uv_12"]) == 0.09273312506660672
    canon = [r for r in cam_rows if float(r["M_cam_from_uv_02"]) == 0.0][0]
    assert float(canon["M_cam_from_uv_00"]) == pytest.approx(np.tan(np.pi / 6))
    assert float(canon["M_cam_from_uv_11"]) == pytest.approx(np.tan(np.pi / 6) * ds.height / ds.width)
    assert float(canon["M_cam_from_uv_22"]) == -1.0

    with open(smoke_dataset / "metadata_camera_trajectories.csv", newline="") as f:
        traj = list(csv.DictReader(f))
    assert {t["Animation"] for t in traj} == {f"{r['scene_name']}_{r['camera_name']}" for r in rows}
    assert all(t["Scene type"] for t in traj)
    meta = json.loads((smoke_dataset / "monolib_synth.json").read_text())
    assert [m["name"] for m in meta["settings"]] == [p["name"] for p in synth.plan(smoke_params)]


def test_at_least_20_classes(smoke_dataset):
    seen = set()
    for s, cam, i in frames_on_disk(smoke_dataset):
        seen |= set(np.unique(h5(files(s, cam, i)["semantic"])).tolist())
    seen.discard(-1)
    assert len(seen) >= 20, sorted(seen)


def test_deterministic(smoke_dataset, smoke_params, tmp_path):
    s = synth.plan(smoke_params)[2]
    out = tmp_path / s["name"]
    synth.render_setting(s, synth._setting_key(s, smoke_params), smoke_params.dataset.width,
                         smoke_params.dataset.height, smoke_params.seed, out)
    a, b = smoke_dataset / s["name"], out
    names = sorted(p.relative_to(a) for p in a.rglob("*.hdf5"))
    assert names == sorted(p.relative_to(b) for p in b.rglob("*.hdf5"))
    for n in names:
        np.testing.assert_array_equal(h5(a / n), h5(b / n), err_msg=str(n))


def test_resume_skips_finished_settings(smoke_dataset, smoke_params, tmp_path, capsys):
    root = tmp_path / "dataset"
    shutil.copytree(smoke_dataset, root)
    victim = synth.plan(smoke_params)[-1]["name"]
    shutil.rmtree(root / victim)
    (root / f".tmp_{victim}_123").mkdir()  # a killed run's leftover
    before = (root / "ai_900_001" / "_detail" / "cam_00" / "camera_keyframe_positions.hdf5").stat().st_mtime_ns
    capsys.readouterr()
    synth.render_dataset(smoke_params, root, progress=False)
    out = capsys.readouterr().out
    n = len(synth.plan(smoke_params))
    assert f"{n - 1} already complete (skipped), 1 to render" in out
    assert (root / victim / "_detail" / "metadata_scene.csv").is_file()
    assert not list(root.glob(".tmp_*"))
    assert (root / "ai_900_001" / "_detail" / "cam_00" / "camera_keyframe_positions.hdf5").stat().st_mtime_ns == before
    assert split_rows(root) == split_rows(smoke_dataset)


def test_views_reach_the_outside_and_the_next_room(smoke_dataset):
    """Real depth: windows show unlabelled outside geometry 10 to 80 m away and the sky (no depth); the
    cameras walk as Hypersim's (steps of at most 1.5 m across and 0.25 m up or down)."""
    far, outside, sky, total = 0, 0, 0, 0
    for s, cam, i in frames_on_disk(smoke_dataset):
        f = files(s, cam, i)
        depth, sem = h5(f["depth_meters"]).astype(np.float64), h5(f["semantic"])
        total += depth.size
        far += int((depth > 10).sum())
        outside += int(((sem == -1) & np.isfinite(depth)).sum())
        sky += int(np.isnan(depth).sum())
    assert far / total > 0.01 and outside / total > 0.005 and sky > 0
    for s in sorted(smoke_dataset.glob("ai_*")):
        for cam in (s / "_detail").glob("cam_*"):
            t = h5(cam / "camera_keyframe_positions.hdf5") * mpau_of(s)
            step = np.diff(t, axis=0)
            assert (np.hypot(step[:, 0], step[:, 1]) <= 1.5 + 1e-9).all()
            assert (np.abs(step[:, 2]) <= 0.25 + 1e-9).all()


def test_light_falls_off_across_a_wall():
    """Real light: one wall's HDR radiance varies within a view (windows, lamps, corners), well beyond
    the 4% of its paint's texture."""
    study = _tiny_study()
    s = synth.plan(study)[0]
    fam, lay, mesh, scenes, r = synth.build_setting(s, study.seed)
    from monolib.data.hypersim import Camera

    rays = Camera.canonical(64, 48).rays(48, 64)
    spreads = []
    for eyes, Rs, _ in scenes:
        fo = synth.render_frame(r, rays, eyes[0], Rs[0], 1.0)
        wall = fo.semantic == 1
        if wall.sum() > 50:
            spreads.append(np.log(fo.color[wall].mean(axis=1)).std())
    assert spreads and max(spreads) > 0.25, spreads


def test_a_damaged_render_is_rendered_again(smoke_dataset, smoke_params, tmp_path, capsys):
    """A truncated depth_meters.hdf5 of a finished setting is noticed by its size, named, and the setting
    rendered again to the same bytes; the other settings are kept."""
    root = tmp_path / "dataset"
    shutil.copytree(smoke_dataset, root)
    victim = synth.plan(smoke_params)[1]["name"]
    depth = root / victim / "images" / "scene_cam_00_geometry_hdf5" / "frame.0000.depth_meters.hdf5"
    whole = depth.read_bytes()
    depth.write_bytes(whole[: len(whole) // 2])
    (root / victim / "images" / "scene_cam_00_final_preview" / "frame.0001.tonemap.jpg").unlink()
    marker = json.loads((root / victim / "_detail" / "monolib_synth_setting.json").read_text())
    assert len(marker["files"]) == sum(1 for p in (smoke_dataset / victim).rglob("*") if p.is_file()) - 1
    capsys.readouterr()
    synth.render_dataset(smoke_params, root, progress=False)
    out = capsys.readouterr().out
    n = len(synth.plan(smoke_params))
    assert f"{victim}: images/scene_cam_00_final_preview/frame.0001.tonemap.jpg and 1 more missing or not the " \
           "size rendered" in out
    assert f"{n - 1} already complete (skipped), 1 to render" in out
    assert depth.read_bytes() == whole
    np.testing.assert_array_equal(h5(depth), h5(smoke_dataset / depth.relative_to(root)))
    assert not list((root / ".aside").glob(f"{victim}@*")) if (root / ".aside").exists() else True


def test_tilt_shift_setting_through_the_reader(smoke_dataset):
    from monolib.data.hypersim import HypersimDataset

    meta = json.loads((smoke_dataset / "monolib_synth.json").read_text())
    tilt = [m["name"] for m in meta["settings"] if m["tilt_shift"]]
    assert tilt
    ds = HypersimDataset(smoke_dataset)
    checked = 0
    for name in tilt:
        assert not ds.camera(name).is_canonical
        mpau = ds.meters_per_asset_unit(name)
        for f in ds.frames(name):
            floor = f.semantic == 2
            if floor.sum() < 50:
                continue
            z = f.points_world()[..., 2][floor]
            assert np.abs(np.median(z)) < 0.03 and np.percentile(np.abs(z), 95) < 0.03, f
            # planar depth from the reader == depth along the camera axis of the written positions
            R, t = f.pose()
            pos = h5(f.files["position"]).astype(np.float64)
            p_cam = (pos - t) @ R * mpau
            ok = ~np.isnan(f.depth)
            np.testing.assert_allclose(f.depth[ok], -p_cam[..., 2][ok], atol=0.02, rtol=3e-3)
            checked += 1
    assert checked > 0


def test_a_larger_training_split_keeps_quicks_test_split_and_training_settings():
    """`dataset.base_train_settings`: the test settings are quick's exactly (the same dicts: the same renders), the
    first 48 training settings are quick's but for their frame count, and the settings after them are new training
    families, about `dim_fraction` of them dim and none tilt-shift."""
    quick = params.load_study("quick")
    for n, frames in ((96, 40), (144, 60)):
        big = params.load_study("quick")
        big.dataset.train_settings, big.dataset.train_frames_per_setting = n, frames
        big.dataset.base_train_settings = 48
        small, large = synth.plan(quick), synth.plan(big)
        n_test = quick.dataset.test_settings + quick.dataset.test_siblings
        assert large[:n_test] == small[:n_test]
        assert [dict(s, frames=frames) for s in small[n_test:]] == large[n_test:len(small)]
        extra = large[len(small):]
        assert len(extra) == n - 48 and {s["split"] for s in extra} == {"train"}
        assert not any(s["tilt_shift"] for s in extra)
        assert sum(s["dim"] for s in extra) == math.ceil(quick.dataset.dim_fraction * len(extra))
        assert len({s["name"] for s in large}) == len(large)
        assert min(s["family"] for s in extra) > max(s["family"] for s in small)


def test_every_setting_of_a_large_plan_has_a_hypersim_name():
    """The zoo's mini-Hypersim has more than 100 families: their volumes wrap from ai_999 to ai_000, so every name
    is ai_VVV_NNN (which the reader requires: it skips a folder named otherwise, such as ai_1000_001, so a
    family's settings would be lost without a word), and names stay unique."""
    from monolib.data.hypersim import SETTING_RE

    zoo = params.load_study("zoo")
    plan = synth.plan(zoo)
    names = [s["name"] for s in plan]
    assert len(plan) == zoo.dataset.train_settings + zoo.dataset.test_settings + zoo.dataset.test_siblings
    assert all(SETTING_RE.match(n) for n in names), [n for n in names if not SETTING_RE.match(n)][:3]
    assert len(set(names)) == len(names)
    too_many = params.load_study("zoo")
    too_many.dataset.train_settings = 2002
    with pytest.raises(ValueError, match="at most 1000"):
        synth.plan(too_many)
