"""The cameras of the mini-Hypersim: the camera models (the canonical one, ai_037_002's tilt-shift one), the
trajectories of a setting's scenes (`make_trajectories`), their exposures and the views turned away from walls at
arm's length (`refine_views`)."""
from __future__ import annotations

import math

import numpy as np

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
