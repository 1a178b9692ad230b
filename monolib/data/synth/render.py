"""Ray casting and shading (embree through trimesh): the `Renderer` of one setting's mesh and `render_frame`, one
frame's colour, depth, positions, semantic, instance and render-entity images."""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional

import numpy as np

from monolib.data.synth.materials import _albedo
from monolib.data.synth.mesh import SceneMesh
from monolib.data.synth.rooms import Layout


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
