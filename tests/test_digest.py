"""The dataset's digest (`monolib.data.digest`) and `monolib verify` reading it before any mean."""
import shutil

from monolib.data import digest
from monolib.io import write_json
from monolib.report import verify


def hypersim_tree(root, settings=("ai_900_001", "ai_900_002"), frames=3):
    """Files in the Hypersim layout: per setting, frames of two kinds and a camera file; metadata at the top."""
    for s in settings:
        geo = root / s / "images" / "scene_cam_00_geometry_hdf5"
        geo.mkdir(parents=True)
        for i in range(frames):
            (geo / f"frame.{i:04d}.depth_meters.hdf5").write_bytes(bytes([i, 1, 2, 3]) * 64)
            (geo / f"frame.{i:04d}.semantic.hdf5").write_bytes(bytes([i, 9]) * 32)
        (root / s / "_detail").mkdir()
        (root / s / "_detail" / "metadata_cameras.csv").write_text("camera_name\ncam_00\n")
    (root / "metadata_images_split_scene_v1.csv").write_text("scene_name,split_partition_name\n")
    return root


def test_the_digest_names_the_setting_and_kind_that_changed(tmp_path):
    root = hypersim_tree(tmp_path / "a")
    before = digest.digest(root)
    assert before == digest.digest(shutil.copytree(root, tmp_path / "b"))  # where it lies does not matter
    assert before["files"] == 15 and set(before["settings"]) == {"ai_900_001", "ai_900_002"}
    assert set(before["settings"]["ai_900_001"]["kinds"]) == {"depth_meters.hdf5", "semantic.hdf5",
                                                              "metadata_cameras.csv"}
    assert digest.differences(before, before) == []
    f = root / "ai_900_002" / "images" / "scene_cam_00_geometry_hdf5" / "frame.0001.semantic.hdf5"
    f.write_bytes(f.read_bytes()[:-1] + b"\x00")  # one byte
    after = digest.digest(root)
    assert after["settings"]["ai_900_001"] == before["settings"]["ai_900_001"]
    assert digest.differences(before, after) == ["setting ai_900_002: semantic.hdf5 (3 files) differ"]
    f.rename(f.with_name("frame.0009.semantic.hdf5"))  # a renamed file changes the digest as a changed byte does
    assert digest.digest(root)["settings"]["ai_900_002"]["sha256"] != after["settings"]["ai_900_002"]["sha256"]
    shutil.rmtree(root / "ai_900_001")
    (root / "metadata_images_split_scene_v1.csv").write_text("other\n")
    lines = digest.differences(before, digest.digest(root))
    assert lines[:2] == ["metadata_images_split_scene_v1.csv: differs",
                         "setting ai_900_001: missing from the fresh dataset"]


def test_verify_compares_the_dataset_first_and_names_what_differs(tmp_path):
    committed, fresh = tmp_path / "committed", tmp_path / "fresh"
    for folder in (committed, fresh):
        folder.mkdir()
    data = hypersim_tree(tmp_path / "data")
    write_json(committed / digest.FILE, digest.digest(data))
    write_json(fresh / digest.FILE, digest.digest(data))
    v = verify.compare("nostudy", fresh, committed)
    assert v.ok and v.lines()[0].startswith("dataset: identical to the committed one (15 files in 2 settings")
    (data / "ai_900_001" / "_detail" / "metadata_cameras.csv").write_text("camera_name\ncam_01\n")
    write_json(fresh / digest.FILE, digest.digest(data))
    v = verify.compare("nostudy", fresh, committed)
    assert v.problems == ["dataset: setting ai_900_001: metadata_cameras.csv (1 file) differ"]
    assert v.lines()[0].startswith("dataset: differs from the committed one in 1 place(s)")
    (fresh / digest.FILE).unlink()
    assert "missing" in verify.compare("nostudy", fresh, committed).problems[0]


def test_a_setting_whose_marker_alone_differs_holds_the_same_data(tmp_path):
    """The marker holds the key (code and library versions) a setting was rendered under: new code that renders the
    same files is information for `verify`, not a problem; a changed file next to it is one."""
    committed, fresh = tmp_path / "committed", tmp_path / "fresh"
    for folder in (committed, fresh):
        folder.mkdir()
    data = hypersim_tree(tmp_path / "data")
    marker = data / "ai_900_002" / "_detail" / digest.MARKER
    marker.write_text('{"key": {"code": "a"}}')
    write_json(committed / digest.FILE, digest.digest(data))
    marker.write_text('{"key": {"code": "b"}}')
    write_json(fresh / digest.FILE, digest.digest(data))
    a, b = digest.read(committed / digest.FILE), digest.read(fresh / digest.FILE)
    assert a["sha256"] != b["sha256"] and digest.differences(a, b) == [] and digest.markers_only(a, b) == ["ai_900_002"]
    v = verify.compare("nostudy", fresh, committed)
    assert v.ok and "every rendered file identical" in v.lines()[0] and "markers of 1 settings differ" in v.lines()[0]
    (data / "ai_900_002" / "_detail" / "metadata_cameras.csv").write_text("camera_name\ncam_01\n")
    write_json(fresh / digest.FILE, digest.digest(data))
    v = verify.compare("nostudy", fresh, committed)
    assert v.problems == ["dataset: setting ai_900_002: metadata_cameras.csv (1 file), "
                          "monolib_synth_setting.json (1 file) differ"]
