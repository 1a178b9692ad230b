"""Ray casting (Embree pinned to its AVX2 kernels: `raycast`) and shading: the `Renderer` of one setting's mesh and
`render_frame`, one frame's colour, depth, positions, semantic, instance and render-entity images."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Optional

import numpy as np

from monolib.data import exact
from monolib.data.synth.materials import _albedo
from monolib.data.synth.mesh import SceneMesh
from monolib.data.synth.raycast import RayCaster
from monolib.data.synth.rooms import Layout


class Renderer:
    """Ray caster + shader for one setting's mesh. Where faces tie for a ray (two parts' faces in one plane, or faces
    meeting at an edge) or a shadow ray grazes an edge, the answer is Embree's (the CPU's rounding decides) or, with
    `exact_ties` (``dataset.coplanar: exact``, the default), the one `raycast.ExactHits` decides in float64 (for an
    image's rays and their shadow rays, with the neighbouring pixels' faces as candidates)."""

    def __init__(self, mesh: SceneMesh, lay: Layout, exact_ties: bool = False):
        import trimesh

        self.mesh = mesh
        self.lay = lay
        self.normals = np.asarray(trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).face_normals)
        self.v0 = mesh.vertices[mesh.faces[:, 0]]
        self.caster = RayCaster(mesh.vertices, mesh.faces, owner=mesh.face_part if exact_ties else None)

    def cast(self, origin: np.ndarray, dirs: np.ndarray, shape: Optional[tuple[int, int]] = None):
        """Primary rays from one origin: (face index or -1, distance along unit dirs); `shape`: the rays are an
        image's (rows, columns), row by row."""
        o = np.broadcast_to(origin, dirs.shape)
        tri = self.caster.first(o, dirs, shape)
        hit = tri >= 0
        t = np.full(len(dirs), np.nan)
        n = self.normals[tri[hit]]
        t[hit] = exact.dot(self.v0[tri[hit]] - origin, n) / exact.dot(dirs[hit], n)
        return tri, t

    def visible(self, origin: np.ndarray, dirs: np.ndarray, dist: np.ndarray, image: Optional[tuple] = None):
        """Whether nothing lies between each origin and the point `dist` along its unit direction (shadow rays;
        `image`: (shape, pixels), the image pixel each ray starts from, which decides ties with `exact_ties`)."""
        shape, pixels = image if image is not None else (None, None)
        return ~self.caster.occluded(origin, dirs, dist, shape, pixels)

    def _lit_from(self, origin: np.ndarray, n: np.ndarray, idx: np.ndarray, point: np.ndarray, margin: float,
                  facing: Optional[np.ndarray] = None, image: Optional[tuple] = None):
        """Of the points `idx` (offset `origin`, normals `n`), those that face `point` and see it (a shadow ray
        stopping `margin` short of it; `facing`: and that lie in front of a window of that inward normal): their
        indices, cosine towards the point, distance and unit direction. `image`: (shape, pixel of each point)."""
        L = point - origin[idx]
        dist = exact.norm(L)
        L /= dist[:, None]
        cos = exact.dot(n[idx], L)
        lit = cos > 0
        if facing is not None:
            lit &= -exact.matmul(L, facing) > 0
        k = idx[lit]
        vis = self.visible(origin[k], L[lit], dist[lit] - margin, None if image is None else (image[0], image[1][k]))
        return k[vis], cos[lit][vis], dist[lit][vis], L[lit][vis]

    def shade(self, tri: np.ndarray, pts: np.ndarray, dirs: np.ndarray, image: Optional[tuple] = None) -> np.ndarray:
        """(n, 3) linear radiance of hit points `pts` on faces `tri` seen along `dirs`; `image`: (shape, pixels), the
        image's (rows, columns) and the pixel of each point, which shadow rays read to decide ties.

        Inside: the light bounced around the rooms (`Layout.ambient`), darker in the corners and near the floor;
        every point light (ceiling fixtures and lamps) with its inverse-square fall-off and the shadows of what
        stands between; the sky through each window (a small area light at its centre: both cosines over the
        squared distance, shadowed); the sun, where a shadow ray towards it leaves the house (its patches through
        the windows). Outside (unlabelled geometry): the sky from above and the sun."""
        m, lay = self.mesh, self.lay
        part = m.face_part[tri]
        n = self.normals[tri]
        flip = exact.dot(n, dirs) > 0
        n[flip] *= -1
        albedo = np.zeros_like(pts)
        emission = np.zeros_like(pts)
        mats = m.part_mat[part]
        ph = np.c_[pts, np.ones(len(pts))]
        for mi in np.unique(mats):
            sel = mats == mi
            inv = m.part_inv[part[sel]]
            local = exact.dot(inv[:, :3, :], ph[sel][:, None, :])
            mat = m.materials[mi]
            albedo[sel] = _albedo(mat, local)
            emission[sel] = mat.emission
        outside = m.part_sem[part] < 0
        inside = ~outside
        light = np.zeros_like(pts)
        # bounced light, darker towards walls, corners and the floor
        x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
        depth_in = np.full(len(pts), -np.inf)
        for x0, y0, x1, y1 in lay.rooms:
            depth_in = np.maximum(depth_in, np.minimum(np.minimum(x - x0, x1 - x), np.minimum(y - y0, y1 - y)))
        ao = (0.45 + 0.55 * (1.0 - exact.exp(-np.clip(depth_in, 0.0, None) / 0.7)))
        ao *= (0.7 + 0.3 * np.clip(z / 0.5, 0, 1)) * (0.85 + 0.15 * np.clip((lay.H - z) / 0.4, 0, 1))
        light[inside] = lay.ambient * ao[inside, None]
        light[outside] = lay.sky * (0.5 + 0.5 * np.clip(n[outside, 2], 0, 1))[:, None]
        origin = pts + n * 2e-3
        idx_in = np.flatnonzero(inside)
        for lp, lrgb in lay.lights:
            k, cos, dist, _L = self._lit_from(origin, n, idx_in, lp, 0.05, image=image)
            light[k] += lrgb * (cos / np.maximum(dist * dist, 0.09))[:, None]
        for centre, normal, area in lay.windows:
            k, cos, dist, L = self._lit_from(origin, n, idx_in, centre, 0.02, facing=normal, image=image)
            w = cos * -exact.matmul(L, normal) * area / (math.pi * np.maximum(dist * dist, area))
            light[k] += lay.sky * w[:, None]
        if lay.sun is not None:
            sun_dir, sun_rgb = lay.sun
            cos = exact.matmul(n, sun_dir)
            lit = np.flatnonzero(cos > 0)
            vis = self.visible(origin[lit], np.broadcast_to(sun_dir, (len(lit), 3)), np.full(len(lit), 500.0),
                               None if image is None else (image[0], image[1][lit]))
            light[lit[vis]] += sun_rgb * cos[lit[vis], None]
        glow = emission * (1.0 if lay.lights else 0.1)
        return albedo * light + glow


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
    d = exact.normalize(exact.matmul(rays_cam.reshape(-1, 3), R.T))
    tri, t = r.cast(eye, d, (Hh, Ww))
    t1 = time.perf_counter()
    hit = tri >= 0
    pts = eye + d[hit] * t[hit, None]
    col = np.zeros((len(d), 3))
    col[hit] = r.shade(tri[hit], pts, d[hit], ((Hh, Ww), np.flatnonzero(hit))) * exposure
    col[~hit] = r.lay.sky * exposure * (1.0 + 0.6 * np.clip(d[~hit, 2:3], 0, 1))  # the sky: no depth, no entity
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
