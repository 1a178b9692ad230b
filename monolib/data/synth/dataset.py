"""The whole mini-Hypersim of a study: the `plan` of its settings (families, splits, dim and tilt-shift settings),
their keys (`_setting_key`), `render_dataset` (resumable: finished settings kept, renders in ``.tmp_*`` folders of a
host and process, settings of another key set aside in ``.aside/`` and restored), the dataset-level metadata files,
and `benchmark`."""
from __future__ import annotations

import hashlib
import json
import math
import multiprocessing as mp
import os
import shutil
import socket
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Optional

import numpy as np

from monolib.data.synth.cameras import FOV_X, _camera_M, _camera_proj
from monolib.data.synth.rooms import ROOM_TYPES, SCENE_TYPE_LABEL
from monolib.data.synth.setting import _write_csv, broken_files, render_setting
from monolib.io import move_aside, write_json
from monolib.progress import tqdm
from monolib.versions import code_version


VOLUME0 = 900  # families are volumes ai_900, ai_901, ... wrapping to ai_000 after ai_999 (3 digits, as in Hypersim)
FORMAT_VERSION = 6  # bump when the generator changes: finished settings with another version are re-rendered

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
    # dim and tilt-shift drawn over the settings of the base plan (every setting without `base_train_settings`);
    # the settings after it draw their dim ones from their own stream and have no tilt-shift camera
    base = total if ds.base_train_settings is None else total - n_train + int(ds.base_train_settings)
    n_dim = int(math.ceil(ds.dim_fraction * base - 1e-9))
    dim_set = set(rng.permutation(base)[:n_dim].tolist())
    n_extra_dim = int(math.ceil(ds.dim_fraction * (total - base) - 1e-9))
    extra = np.random.default_rng([study.seed, 2718, 1]).permutation(total - base)[:n_extra_dim]
    dim_set |= {base + int(i) for i in extra}
    n_tilt = min(base, int(ds.tilt_shift_settings))
    tilt_set = set(np.round(np.linspace(0, base, n_tilt, endpoint=False)).astype(int).tolist()) if n_tilt else set()
    for i, s in enumerate(settings):
        s["index"] = i
        s["name"] = f"ai_{(VOLUME0 + s['family']) % 1000:03d}_{s['member'] + 1:03d}"
        s["room_type"] = fam_room[s["family"]]
        s["scene_type"] = SCENE_TYPE_LABEL[s["room_type"]]
        s["dim"] = i in dim_set
        s["tilt_shift"] = i in tilt_set
        s["meters_per_asset_unit"] = 0.0254 if i % 4 == 2 else 0.01
        if ds.coplanar != "embree":  # a plan without it is Embree's, as every plan before the choice existed
            s["coplanar"] = ds.coplanar
    return settings


def _setting_key(s: dict, study) -> dict:
    ds = study.dataset

    return {"version": FORMAT_VERSION, "code": code_version("dataset"), "seed": int(study.seed),
            "width": int(ds.width), "height": int(ds.height), "family_size": int(ds.family_size), "setting": s}


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
    """The info of a setting rendered with `key` and still whole (every file its marker lists, at the size it was
    written), else None. A render whose files were damaged afterwards (truncated, deleted) is named on stdout, removed
    and so rendered again; a marker without a file list (written before the check existed) is trusted."""
    marker = final / "_detail" / "monolib_synth_setting.json"
    if not marker.is_file():
        return None
    try:
        data = json.loads(marker.read_text())
    except (OSError, ValueError):
        return None
    if data.get("key") != json.loads(json.dumps(key)):
        return None
    broken = broken_files(final, data.get("files", {}))
    if broken:
        more = f" and {len(broken) - 1} more" if len(broken) > 1 else ""
        print(f"monolib.data.synth: {final}: {broken[0]}{more} missing or not the size rendered; "
              f"rendering the setting again", flush=True)
        shutil.rmtree(final)
        return None
    return data.get("info")


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
        print(f"monolib.data.synth: {len(stale)} synthetic settings in {out_dir} are not in this study "
              "(kept; not read)", flush=True)
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
        import threadpoolctl

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
            traj_rows.append([f"{s['name']}_{cname}", "", "", "", "", "", "", s["scene_type"], "monolib.data.synth",
                              ""])
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
                                                    "test_siblings", "family_size", "frames_per_setting",
                                                    "train_frames_per_setting", "dim_fraction", "tilt_shift_settings")},
            "settings": [{k: infos[s["name"]].get(k) for k in
                          ("name", "index", "family", "member", "room_type", "scene_type", "split", "dim",
                           "tilt_shift", "meters_per_asset_unit", "frames", "scenes", "frames_per_scene", "classes",
                           "room_size_m", "num_lights")} for s in settings]}
    write_json(out_dir / "monolib_synth.json", meta)


def benchmark(width: int = 256, height: int = 192, frames: int = 20, seed: int = 0) -> dict:
    """Render one setting's frames into a temporary folder; print and return frames per second by stage."""
    ds = SimpleNamespace(width=width, height=height, train_settings=0, test_settings=1, test_siblings=0, family_size=1,
                         frames_per_setting=frames, train_frames_per_setting=frames, dim_fraction=0.0,
                         tilt_shift_settings=0, base_train_settings=None, coplanar="exact", workers=1)
    study = SimpleNamespace(seed=seed, dataset=ds)
    s = plan(study)[0]
    timing: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        render_setting(s, _setting_key(s, study), width, height, seed, Path(tmp) / s["name"], timing)
        total = time.perf_counter() - t0
    n = timing.get("frames", 0)
    res = {"width": width, "height": height, "frames": n, "total_s": total, "build_s": timing.get("build", 0.0),
           "cast_ms_per_frame": 1000 * timing.get("cast", 0.0) / n,
           "shade_ms_per_frame": 1000 * timing.get("shade", 0.0) / n,
           "write_ms_per_frame": 1000 * timing.get("write", 0.0) / n, "fps": n / total}
    print(f"monolib.data.synth benchmark {width}x{height}, {n} frames: {res['fps']:.2f} frames/s overall; per frame: "
          f"cast {res['cast_ms_per_frame']:.1f} ms, shade (+shadows) {res['shade_ms_per_frame']:.1f} ms, "
          f"write {res['write_ms_per_frame']:.1f} ms; scene build {res['build_s']:.2f} s")
    return res
