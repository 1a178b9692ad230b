"""The ray caster of the mini-Hypersim: Embree (through embreex) on a device pinned to Embree's AVX2 kernels.

Embree picks its kernels for the CPU's widest ISA. Its AVX-512 and AVX2 kernels round a ray's hit test
differently, so a ray within float32 rounding of a triangle's edge hits the other triangle (or, in a shadow ray,
misses the occluder). One such ray moves a camera of `cameras.make_trajectories`, which scores candidate views with
ray casts, so the whole setting changes. Measured at quick's size: rendered on an AVX-512 CPU with Embree's default
kernels, every one of the 72 settings differed from the AVX2 CPU's; with this device pinned to AVX2, the same files,
byte for byte (docs/reproducibility.md).

embreex creates its devices without a configuration string (`EmbreeDevice()`), so `device` creates one with
``isa=avx2`` through Embree's own C API (ctypes, on the library embreex loaded) and hands it to an `EmbreeDevice`
in place of the one embreex made (which is released). The swap writes the device pointer, the one field of embreex's
`EmbreeDevice`, after the object's header; it checks first that the object has exactly that size.

A CPU without AVX2 or FMA (none made since 2015 among the x86-64 CPUs this project has met) runs Embree's default
kernels, says so once on stderr, and may render other bytes; `make verify` names the settings that differ.

`RayCaster` does the arithmetic trimesh's `RayMeshIntersector` did before (vertices shifted by their minimum,
directions normalised again in float32 and float64) in elementwise numpy only, so the rays' float32 inputs are the
same on every CPU.

Pinning the ISA makes every AMD CPU with AVX2 cast the same hits (the Zen 3 and Zen 4 EPYCs, measured at quick's
size), but not every x86 CPU: Embree's kernels divide by an approximate reciprocal (``vrcpps`` and one Newton step
with AVX2), and Intel's and AMD's ``vrcpps`` return other approximations. Where a ray meets two faces at the same
distance (faces of two parts in one plane: a door in its wall's opening, two floors that overlap, a rug; or two faces
meeting at an edge) which face Embree reports depends on those last bits: on an Intel Xeon (Sapphire Rapids) every
one of quick's 72 settings rendered differently from the AMD EPYCs' (on that Xeon, Embree's AVX2 and AVX-512
kernels disagree on 0.8 % of a setting's pixels, and a moved pixel can move a camera, which scores views with ray
casts). With ``dataset.coplanar: exact``
(a study's choice; the default ``embree`` keeps the renders every committed study was made from) the scene is in
Embree's robust mode (`set_robust`) and `ExactHits` decides each first hit in float64 among the faces that could
hold it: under Embree's AVX2 and AVX-512 kernels (whose reciprocals differ as two vendors' do) quick's settings then
render the same files but for a few pixels (docs/reproducibility.md). What it leaves to Embree: shadow rays (in
robust mode), and a tie between faces that none of the candidates above names.
"""
from __future__ import annotations

import ctypes
import functools
import glob
import os
import sys
from typing import Optional

import numpy as np

from monolib.data import exact

ISA: Optional[str] = "avx2"  # Embree's kernels for every ray cast of the dataset (None: Embree's choice)
_PINNED = "pinned"
_warned = False


@functools.lru_cache(maxsize=None)
def _embree_library() -> ctypes.CDLL:
    import embreex

    found = sorted(glob.glob(os.path.join(os.path.dirname(embreex.__file__), "..", "embreex.libs", "libembree4*")))
    if not found:
        raise RuntimeError(f"{os.path.dirname(embreex.__file__)}: Embree's library (embreex.libs/libembree4*) not "
                           "found beside embreex: the ray caster cannot pin Embree's ISA")
    lib = ctypes.CDLL(found[0])
    lib.rtcNewDevice.restype = ctypes.c_void_p
    lib.rtcNewDevice.argtypes = [ctypes.c_char_p]
    lib.rtcReleaseDevice.argtypes = [ctypes.c_void_p]
    lib.rtcGetDeviceError.argtypes = [ctypes.c_void_p]
    lib.rtcSetSceneFlags.argtypes = [ctypes.c_void_p, ctypes.c_int]
    lib.rtcGetSceneFlags.argtypes = [ctypes.c_void_p]
    return lib


def _first_field(obj, what: str) -> ctypes.c_void_p:
    """The pointer an embreex object holds first after its Python header (an `EmbreeDevice`'s device, an
    `EmbreeScene`'s scene), as a writable ctypes slot; the object's size is checked to hold one."""
    if type(obj).__basicsize__ < object.__basicsize__ + ctypes.sizeof(ctypes.c_void_p):
        raise RuntimeError(f"embreex's {what} holds no pointer after its header: this embreex is not the one the ray "
                           "caster knows (see requirements.lock)")
    return ctypes.c_void_p.from_address(id(obj) + object.__basicsize__)


def cpu_has_isa(isa: str = ISA) -> bool:
    """Whether this CPU runs Embree's `isa` kernels (AVX2 needs AVX2 and FMA3)."""
    from numpy._core._multiarray_umath import __cpu_features__ as have

    need = {"avx2": ["AVX2", "FMA3"], "avx": ["AVX"], "sse4.2": ["SSE42"], "sse2": ["SSE2"]}.get(isa.lower())
    if need is None:
        raise ValueError(f"Embree ISA {isa!r}: expected one of avx2, avx, sse4.2, sse2")
    return all(have.get(f) for f in need)


def device(isa: Optional[str] = ISA, config: str = ""):
    """An embreex `EmbreeDevice` whose Embree device runs the `isa` kernels (None: Embree's choice for this CPU),
    with `config` appended to its configuration string (e.g. ``threads=1``, ``verbose=1``)."""
    import embreex.rtcore as rtc

    global _warned
    if isa is not None and not cpu_has_isa(isa):
        if not _warned:
            print(f"monolib.data.synth.raycast: this CPU lacks Embree's {isa} kernels; Embree runs its default ones, "
                  "and the rendered dataset may differ from the committed digest", file=sys.stderr)
            _warned = True
        isa = None
    cfg = " ".join(x for x in [f"isa={isa}" if isa else "", config] if x)
    dev = rtc.EmbreeDevice()
    if not cfg:
        return dev
    pointer = ctypes.sizeof(ctypes.c_void_p)
    if type(dev).__basicsize__ != object.__basicsize__ + pointer:
        raise RuntimeError(f"embreex's EmbreeDevice is {type(dev).__basicsize__} bytes, not a header and one "
                           "pointer: this embreex is not the one the ray caster knows (see requirements.lock)")
    lib = _embree_library()
    new = lib.rtcNewDevice(cfg.encode())
    if not new or lib.rtcGetDeviceError(new) != 0:
        raise RuntimeError(f"Embree refused the device configuration {cfg!r}")
    slot = _first_field(dev, "EmbreeDevice")
    old, slot.value = slot.value, new
    lib.rtcReleaseDevice(old)
    return dev


RTC_SCENE_FLAG_ROBUST = 1 << 2  # embree4/rtcore_scene.h


def set_robust(scene) -> None:
    """Embree's robust mode on an embreex `EmbreeScene`, before its first query commits it: conservative box tests and
    watertight triangle tests (no ray slips through an edge two faces share, whatever the reciprocal's last bits).
    The scene pointer is the object's first field; Embree's own report of the flags checks the write."""
    lib = _embree_library()
    pointer = _first_field(scene, "EmbreeScene").value
    lib.rtcSetSceneFlags(pointer, RTC_SCENE_FLAG_ROBUST)
    if lib.rtcGetSceneFlags(pointer) != RTC_SCENE_FLAG_ROBUST:
        raise RuntimeError("Embree did not take the robust flag: this embreex is not the one the ray caster knows")


PLANE_DECIMALS = 6  # faces whose unit normals agree to 1e-6 ...
PLANE_GAP = 1e-4  # ... and whose offsets lie within 0.1 mm of the next one's share a plane (surfaces microns apart,
# a door in its frame, are ties for float32 kernels as much as coplanar ones)
VERTEX_DECIMALS = 6  # vertices within 1e-6 m are one corner (faces meeting there are neighbours)
CONTAIN_TOLERANCE = 1e-6  # metres: faces of one plane whose boxes overlap by more than this can hide each other
EDGE_MARGIN = 1e-5  # metres: a hit this close to its face's edge is decided among the face's neighbours


class ExactHits:
    """The first hits of rays decided in float64 among the faces that could be hit at Embree's hit point (see the
    module's text), so that the answer does not depend on which of them Embree's float32 kernels reported.

    Faces are grouped by plane (unit normals within `PLANE_DECIMALS`, offsets within `PLANE_GAP` of the next); each
    face is described in its plane's two dominant axes, and a ray meets every face of a plane at one distance, the
    plane's. The candidates of a ray that Embree says hits face k: k; where the hit point lies within `EDGE_MARGIN`
    of k's edge, every face that shares a corner with k (`VERTEX_DECIMALS`) or k's plane; deeper inside k, the faces
    of other owners that overlap k in its plane (those facing the same side, when k faces the ray); for the rays of
    an image, the faces its neighbouring pixels hit that touch neither k's corners nor its plane, with their
    corners' faces (`resolve`'s `shape`). Of the candidates that contain their own hit point (2-D edge functions) in
    front of the origin: the nearest, then the one facing the ray, then the highest owner, then the lowest index.
    Elementwise float64 arithmetic only (`monolib.data.exact`), so the answer is the CPU's only through the
    candidates Embree's hits name."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, owner: np.ndarray):
        from scipy import sparse

        faces = np.asarray(faces, dtype=np.int64)
        V = np.asarray(vertices, dtype=np.float64)[faces]
        self.owner = np.asarray(owner).astype(np.int64)
        normal = exact.cross(V[:, 1] - V[:, 0], V[:, 2] - V[:, 0])
        length = exact.norm(normal)
        unit = normal / np.where(length > 0, length, 1.0)[:, None]
        # one sign per plane: its first non-zero component of the normal positive
        lead = np.where(np.abs(unit[:, 0]) > 1e-9, unit[:, 0],
                        np.where(np.abs(unit[:, 1]) > 1e-9, unit[:, 1], unit[:, 2]))
        sign = np.where(lead < 0, -1.0, 1.0)
        _, direction = np.unique(np.round(unit * sign[:, None], PLANE_DECIMALS) + 0.0, axis=0, return_inverse=True)
        direction = direction.reshape(-1)
        offset = exact.dot(unit, V[:, 0]) * sign
        order = np.lexsort((offset, direction))  # one direction's faces along their offsets: a gap starts a plane
        starts = np.r_[True, (np.diff(direction[order]) != 0) | (np.diff(offset[order]) > PLANE_GAP)]
        plane = np.empty(len(faces), np.int64)
        plane[order] = np.cumsum(starts) - 1
        first = np.full(plane.max() + 1, len(faces))
        np.minimum.at(first, plane, np.arange(len(faces)))
        lead_face = first[plane]  # each face's plane described by the plane's first face
        self.unit, self.plane, self.valid = unit, plane, length > 0
        self.normal, self.offset = unit[lead_face], exact.dot(unit[lead_face], V[lead_face, 0])
        drop = np.argmax(np.abs(self.normal), axis=1)
        self.axes = np.array([[1, 2], [0, 2], [0, 1]])[drop]  # (F, 2)
        tri = np.take_along_axis(V, self.axes[:, None, :].repeat(3, axis=1), axis=2)  # (F, 3, 2)
        self.a, self.edge = tri, np.roll(tri, -1, axis=1) - tri
        area = self.edge[:, 0, 0] * (tri[:, 2, 1] - tri[:, 0, 1]) - self.edge[:, 0, 1] * (tri[:, 2, 0] - tri[:, 0, 0])
        self.orient = np.where(area < 0, -1.0, 1.0)
        self.edge_len = np.sqrt(self.edge[..., 0] * self.edge[..., 0] + self.edge[..., 1] * self.edge[..., 1])
        n = len(faces)
        plane_faces = sparse.csr_matrix((np.ones(n), (plane, np.arange(n))))
        corner = np.unique(np.round(V.reshape(-1, 3), VERTEX_DECIMALS) + 0.0, axis=0, return_inverse=True)[1]
        at = sparse.csr_matrix((np.ones(3 * n), (np.repeat(np.arange(n), 3), corner.reshape(-1))))
        self.corners = (at @ at.T).tocsr()  # the faces that share a corner with each face (itself included)
        self.neighbours = (self.corners + plane_faces[plane]).tocsr()  # a corner or the plane shared
        self.neighbour_codes = np.sort(np.repeat(np.arange(n), np.diff(self.neighbours.indptr)) * n
                                       + self.neighbours.indices)
        # pairs of one plane, of two owners, whose boxes overlap by more than the tolerance: where a point deep inside
        # one face can lie inside the other; `same`: the two face the same side
        same_plane = plane_faces[plane].tocoo()
        i, j = same_plane.row, same_plane.col
        pair = (self.owner[i] != self.owner[j]) & self.valid[i] & self.valid[j]
        pair &= ((tri.min(axis=1)[i] + CONTAIN_TOLERANCE < tri.max(axis=1)[j])
                 & (tri.min(axis=1)[j] + CONTAIN_TOLERANCE < tri.max(axis=1)[i])).all(axis=1)
        i, j = i[pair], j[pair]
        same = exact.dot(unit[i], unit[j]) > 0
        self.overlap = sparse.csr_matrix((np.ones(len(i)), (i, j)), shape=(n, n))
        self.overlap_same = sparse.csr_matrix((np.ones(int(same.sum())), (i[same], j[same])), shape=(n, n))

    def _inside(self, face: np.ndarray, o: np.ndarray, d: np.ndarray):
        """(t, signed distance of the point inside the face's nearest edge) of rays (o, d) on `face`'s plane."""
        t = (self.offset[face] - exact.dot(o, self.normal[face])) / exact.dot(d, self.normal[face])
        p = np.take_along_axis(o + d * t[:, None], self.axes[face], axis=1)
        rel = p[:, None, :] - self.a[face]
        e = self.edge[face]
        side = (e[..., 0] * rel[..., 1] - e[..., 1] * rel[..., 0]) * self.orient[face][:, None]
        return t, (side / np.maximum(self.edge_len[face], 1e-300)).min(axis=1)

    def resolve(self, hit: np.ndarray, origins: np.ndarray, dirs: np.ndarray,
                shape: Optional[tuple[int, int]] = None) -> np.ndarray:
        """`hit` (Embree's face index per ray, -1 for none) decided in float64 (see the class); rays in float64.
        `shape` (rows, columns): the rays are an image's, row by row; a ray whose neighbouring pixels hit a face
        that touches neither its own face's corners nor its plane (a silhouette, a seam, the sky's edge) also takes
        that face and the faces of its corners as candidates, hit or missed."""
        out = np.array(hit, copy=True)
        n_faces = len(self.owner)
        o_all = np.broadcast_to(np.asarray(origins, np.float64), np.shape(dirs))
        d_all = np.asarray(dirs, np.float64)
        rays = np.flatnonzero(out >= 0)
        k = out[rays]
        margin = self._inside(k, o_all[rays], d_all[rays])[1]
        near_edge = margin < EDGE_MARGIN
        facing_k = exact.dot(self.unit[k], d_all[rays]) < 0
        # candidate (ray, face) pairs: k itself; near k's edge, the faces of its corners and plane; deeper inside k,
        # the faces of other owners that overlap k in its plane (facing the same side as k, when k faces the ray)
        pr, pf = [rays], [k]
        for sel, table in ((np.flatnonzero(near_edge), self.neighbours),
                           (np.flatnonzero(~near_edge & facing_k), self.overlap_same),
                           (np.flatnonzero(~near_edge & ~facing_k), self.overlap)):
            if len(sel):
                rows = table[k[sel]]
                pr.append(rays[sel][np.repeat(np.arange(len(sel)), np.diff(rows.indptr))])
                pf.append(rows.indices.astype(np.int64))
        if shape is not None and int(np.prod(shape)) == len(out):
            grid = np.pad(np.asarray(hit).reshape(shape), 1, constant_values=-1)
            h, w = shape
            around = np.stack([grid[1 + dy:1 + dy + h, 1 + dx:1 + dx + w].reshape(-1)
                               for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx], axis=1)
            own = np.asarray(hit)[:, None]
            r, c = np.nonzero((around >= 0) & (around != own))
            other = around[r, c]
            code = np.where(own[r, 0] >= 0, own[r, 0], 0) * n_faces + other
            at = np.minimum(np.searchsorted(self.neighbour_codes, code), len(self.neighbour_codes) - 1)
            foreign = (own[r, 0] < 0) | (self.neighbour_codes[at] != code)
            pair = np.unique(r[foreign] * n_faces + other[foreign])
            r, other = pair // n_faces, pair % n_faces
            rows = self.corners[other]
            pr.append(r[np.repeat(np.arange(len(r)), np.diff(rows.indptr))])
            pf.append(rows.indices.astype(np.int64))
        r, f = np.concatenate(pr), np.concatenate(pf)
        keep = self.valid[f]
        r, f = r[keep], f[keep]
        if not len(r):
            return out
        o, d = o_all[r], d_all[r]
        t, inside = self._inside(f, o, d)
        ok = (inside >= 0) & (t > 0)
        r, f, t, d = r[ok], f[ok], t[ok], d[ok]
        facing = exact.dot(self.unit[f], d) < 0
        order = np.lexsort((f, -self.owner[f], ~facing, t, r))  # per ray: nearest, facing, highest owner, index
        best = order[np.r_[True, r[order][1:] != r[order][:-1]]]
        out[r[best]] = f[best]
        return out


class RayCaster:
    """First hits and occlusion of rays against one triangle mesh (metres, float64 in, Embree's float32 inside).
    With `owner` (the part of each face), first hits on a plane of several parts' faces are decided by
    `ExactHits` (and the scene is in Embree's robust mode)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, isa: Optional[str] = _PINNED, config: str = "",
                 owner: Optional[np.ndarray] = None):
        from embreex.mesh_construction import TriangleMesh
        from embreex.rtcore_scene import EmbreeScene

        v = np.asarray(vertices, dtype=np.float64)
        self.exact = None if owner is None else ExactHits(v, faces, owner)
        self.origin = v.min(axis=0)
        self.device = device(ISA if isa == _PINNED else isa, config)  # kept: the scene holds its device's pointer
        self.scene = EmbreeScene(self.device)
        if owner is not None:
            set_robust(self.scene)
        TriangleMesh(scene=self.scene, vertices=(v - self.origin).astype(np.float32),
                     indices=np.asarray(faces).astype(np.int32))

    def _origins(self, origins: np.ndarray) -> np.ndarray:
        return (np.asarray(origins, dtype=np.float64) - self.origin).astype(np.float32)

    def first(self, origins: np.ndarray, dirs: np.ndarray, shape: Optional[tuple[int, int]] = None) -> np.ndarray:
        """Index of the first triangle each ray hits, or -1. The origins are rounded to float32 first; the
        directions to float32 and normalised again (float64 norm of the float32 squares). `shape`: the rays are an
        image's (rows, columns), which `ExactHits` reads."""
        o = np.asarray(origins, dtype=np.float32)
        d = np.asarray(dirs, dtype=np.float32)
        sq = d * d
        norm = np.sqrt(sq[:, 0].astype(np.float64) + sq[:, 1] + sq[:, 2])
        unit = d * np.where(norm > 1e-12, 1.0 / norm, norm)[:, None]
        hit = self.scene.run(self._origins(o), unit.astype(np.float32))
        return hit if self.exact is None else self.exact.resolve(hit, origins, dirs, shape)

    def occluded(self, origins: np.ndarray, dirs: np.ndarray, dists: np.ndarray) -> np.ndarray:
        """Whether something lies along each ray before `dists` (shadow rays; directions taken as they are)."""
        res = self.scene.run(self._origins(origins), np.asarray(dirs).astype(np.float32),
                             dists=np.asarray(dists).astype(np.float32), query="OCCLUDED")
        return res != -1
