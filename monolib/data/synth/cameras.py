"""The cameras of the mini-Hypersim: the camera models (the canonical one, ai_037_002's tilt-shift one), the
trajectories of a setting's scenes (`make_trajectories`: Hypersim's scored random walk, `view_score`) and their
exposures."""
from __future__ import annotations

import math

import numpy as np

from monolib.data import exact
from monolib.data.hypersim import Camera
from monolib.data.synth.render import Renderer
from monolib.data.synth.rooms import Layout


FOV_X = math.pi / 3

# ai_037_002's tilt-shift camera (metadata_camera_parameters.csv of ml-hypersim)
TILT_SHIFT_M = ((0.579607251426182, 0.0, -0.06955286861651404),
                (0.0, 0.4346865334657201, 0.09273312506660672),
                (-0.0, 0.004054126980668954, -1.003909173803896))
TILT_SHIFT_PROJ = (1.7253062268275619, 0.001113868662274642, -0.11942983282195321, 0.0,
                   0.0, 2.2985281393428907, 0.21231970279458348, 0.0,
                   0.0, 0.009300822120943601, -0.9972411188430887, -2.002002002002002,
                   0.0, 0.009282239059762895, -0.9952486290951505, 0.0)


def look_rotation(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """R_world_from_cam for a camera at `eye` looking at `target` (x right, y up, z backward; world z up)."""
    f = target - eye
    f = exact.normalize(f)
    x = exact.normalize(exact.cross(f, [0.0, 0.0, 1.0]))
    z = -f
    y = exact.cross(z, x)
    return np.stack([x, y, z], axis=1)


def _free_floor(lay: Layout, res: float = 0.1):
    """(cell centres x, y, free mask) of the main room's floor where a camera may stand: clear of the walls and of
    every footprint."""
    nx, ny = int(lay.W / res), int(lay.D / res)
    gx, gy = (np.arange(nx) + 0.5) * res, (np.arange(ny) + 0.5) * res
    X, Y = np.meshgrid(gx, gy, indexing="ij")
    free = (X > 0.5) & (X < lay.W - 0.5) & (Y > 0.5) & (Y < lay.D - 0.5)
    for r in lay.rects:
        free &= ~((X > r[0] - 0.25) & (X < r[2] + 0.25) & (Y > r[1] - 0.25) & (Y < r[3] + 0.25))
    if not free.any():
        free = (X > 0.4) & (X < lay.W - 0.4) & (Y > 0.4) & (Y < lay.D - 0.4)
    return gx, gy, free


PROBE_W, PROBE_H = 16, 12


def view_score(r: Renderer, eye: np.ndarray, R: np.ndarray, probe: np.ndarray) -> float:
    """Hypersim's score of a candidate view: (share of valid pixels)^2 x (distinct objects seen), on a 16x12 probe;
    a view closer than 1 m to what it faces (a wall at arm's length) scores less."""
    tri, t = r.cast(eye, exact.matmul(probe, R.T), (PROBE_H, PROBE_W))
    hit = tri >= 0
    if not hit.any():
        return 0.0
    inst = r.mesh.part_inst[r.mesh.face_part[tri[hit]]]
    objects = len(np.unique(inst[inst >= 1]))
    return float(hit.mean() ** 2 * objects * min(1.0, float(np.median(t[hit])) / 1.0))


def make_trajectories(lay: Layout, n_frames: int, seed: int, setting_index: int, r: Renderer) -> list:
    """1 scene for fewer than 12 frames, else 2-3; each: (eyes (n,3) metres, R (n,3,3), look-at (n,3) metres).

    As Hypersim's: each scene starts at a viewpoint an artist would choose (standing height, 1.5-1.7 m, near the
    edge of the free floor, looking across the room towards its far side: the best of 12 such views by
    `view_score`), then takes random-walk steps: the camera up to 1.5 m horizontally and 0.25 m vertically, its
    look-at point up to 3 m, one of 8 candidates drawn in proportion to its `view_score` each time (pitch within
    -30..+12 degrees)."""
    rng = np.random.default_rng([seed, 32452843, setting_index])
    n_scenes = 1 if n_frames < 12 else int(rng.integers(2, 4))  # several trajectories, as in Hypersim
    counts = [n_frames // n_scenes + (1 if k < n_frames % n_scenes else 0) for k in range(n_scenes)]
    gx, gy, free = _free_floor(lay)
    fi, fj = np.nonzero(free)
    cells = np.c_[gx[fi], gy[fj]]
    probe = Camera.canonical(PROBE_W, PROBE_H).rays(PROBE_H, PROBE_W).reshape(-1, 3)
    probe = exact.normalize(probe)
    x0 = min(b[0] for b in lay.rooms)
    y0 = min(b[1] for b in lay.rooms)
    x1 = max(b[2] for b in lay.rooms)
    y1 = max(b[3] for b in lay.rooms)
    centre = np.array([lay.W / 2, lay.D / 2])

    def is_free(p):
        i, j = int(p[0] / 0.1), int(p[1] / 0.1)
        return 0 <= i < len(gx) and 0 <= j < len(gy) and bool(free[i, j])

    def pose(eye, look):
        reach = max(float(exact.norm(look[:2] - eye[:2])), 0.5)
        look = look.copy()
        look[2] = eye[2] + np.clip(look[2] - eye[2], reach * math.tan(math.radians(-30)),
                                   reach * math.tan(math.radians(12)))
        return look, look_rotation(eye, look)

    scenes = []
    edge = np.hypot(*((cells - centre) / np.maximum(centre, 1e-6)).T)  # 0 at the centre, 1 at the walls
    start_pool = np.flatnonzero(edge > np.quantile(edge, 0.5)) if len(cells) > 4 else np.arange(len(cells))
    for n in counts:
        best = None
        for _ in range(12):
            e2 = cells[int(rng.choice(start_pool))] + rng.uniform(-0.04, 0.04, 2)
            across = 2 * centre - e2 + rng.normal(0, 0.8, 2)  # the far side of the room
            eye = np.r_[e2, rng.uniform(1.5, 1.7)]
            look, R = pose(eye, np.r_[across, rng.uniform(0.5, 1.2)])
            score = view_score(r, eye, R, probe)
            if best is None or score > best[0]:
                best = (score, eye, look, R)
        _, eye, look, R = best
        eyes, looks, Rs = [eye], [look], [R]
        for _ in range(n - 1):
            candidates = []
            for _c in range(8):
                step = rng.uniform(0, 1.5) * np.array([math.cos(a := rng.uniform(0, 2 * math.pi)), math.sin(a)])
                e = np.r_[eye[:2] + step, np.clip(eye[2] + rng.uniform(-0.25, 0.25), 1.1, 1.9)]
                if not is_free(e):
                    continue
                q = look + np.r_[rng.uniform(-3.0, 3.0, 2), rng.uniform(-0.25, 0.25)]
                q[:2] = np.clip(q[:2], [x0 + 0.2, y0 + 0.2], [x1 - 0.2, y1 - 0.2])
                q[2] = np.clip(q[2], 0.2, lay.H - 0.2)
                if exact.norm(q[:2] - e[:2]) < 1.5:
                    q[:2] = e[:2] + (q[:2] - e[:2]) / max(float(exact.norm(q[:2] - e[:2])), 1e-6) * 1.5
                q, Rq = pose(e, q)
                candidates.append((view_score(r, e, Rq, probe), e, q, Rq))
            scores = np.array([c[0] for c in candidates])
            if len(candidates) and scores.sum() > 0:  # a candidate drawn in proportion to its score
                _, eye, look, R = candidates[int(rng.choice(len(candidates), p=scores / scores.sum()))]
            eyes.append(eye)
            looks.append(look)
            Rs.append(R)
        scenes.append((np.array(eyes), np.stack(Rs), np.array(looks)))
    return scenes


def setting_exposure(r: Renderer, scenes: list, compensation: float = 0.7, target: float = 0.5) -> float:
    """The exposure an artist sets for a whole setting (Hypersim: no auto-exposure, one exposure per scene): the
    median radiance of the first view of each trajectory (a 32x24 render) brought `compensation` of the way (in log)
    to `target`, so that dark rooms stay darker than bright ones."""
    rays = Camera.canonical(32, 24).rays(24, 32).reshape(-1, 3)
    rays = exact.normalize(rays)
    values = []
    for eyes, Rs, _looks in scenes:
        d = exact.matmul(rays, Rs[0].T)
        tri, t = r.cast(eyes[0], d, (24, 32))
        hit = tri >= 0
        if hit.any():
            colour = r.shade(tri[hit], eyes[0] + d[hit] * t[hit, None], d[hit], ((24, 32), np.flatnonzero(hit)))
            values.append(exact.matmul(colour, np.array([0.3, 0.59, 0.11])))
    if not values:
        return 1.0
    median = max(float(np.median(np.concatenate(values))), 1e-6)
    return float(exact.exp(compensation * (exact.log(target) - exact.log(median))))


def scene_exposures(rng: np.random.Generator, n: int) -> np.ndarray:
    """Exposure of each frame of one scene: one level per scene (x0.45-2.2) and a 2% flicker, steady along the
    trajectory as in Hypersim's renders."""
    return exact.exp(rng.uniform(exact.log(0.45), exact.log(2.2)) + rng.normal(0, 0.02, n))


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
