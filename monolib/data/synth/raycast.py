"""The ray caster of the mini-Hypersim: Embree (through embreex), its hits decided in float64 (`ExactHits`).

Embree casts in float32, and which of two faces a ray hits where they tie is decided by the last bits of its
arithmetic: faces of two parts in one plane (a door in its wall's opening, two floors that overlap, a rug, a
fixture on the ceiling) or faces meeting at an edge, and for a shadow ray whether it grazes an occluder's edge. Those
bits are the CPU's: Embree picks its kernels for the CPU's widest ISA (its AVX-512 and AVX2 kernels round
otherwise), and its kernels divide by the approximate reciprocal instruction (``vrcpps`` and one Newton step with
AVX2, ``vrcp14ps`` with AVX-512), whose approximation differs between Intel and AMD. One such ray moves a camera of
`cameras.make_trajectories`, which scores candidate views with ray casts, so the whole setting changes: on an Intel
Xeon every one of quick's 72 settings rendered otherwise than on the AMD EPYCs, Embree pinned to the same kernels.

With ``dataset.coplanar: exact`` (the default) the scene is in Embree's robust mode (`set_robust`) and Embree only
names candidates: `ExactHits` decides every first hit and every shadow ray in float64 among the faces that could
hold it, and a ray that passes its Embree face's edge is cast again from beyond it. Quick's 72 settings render to
the same files under Embree's AVX2, AVX-512, AVX and SSE4.2 kernels (docs/reproducibility.md). With ``embree`` (the
renderer of the studies committed before, kept for them) Embree's own hits stand, and the device is pinned to its
AVX2 kernels: the same files on every AMD CPU with AVX2 (two EPYCs measured), not on an Intel one.

embreex creates its devices without a configuration string (`EmbreeDevice()`), so `device` creates one with
``isa=avx2`` through Embree's own C API (ctypes, on the library embreex loaded) and hands it to an `EmbreeDevice`
in place of the one embreex made (which is released). The swap writes the device pointer, the one field of embreex's
`EmbreeDevice`, after the object's header; it checks first that the object has exactly that size. A CPU without
AVX2 or FMA runs Embree's default kernels and says so once on stderr.

`RayCaster` does the arithmetic trimesh's `RayMeshIntersector` did before (vertices shifted by their minimum,
directions normalised again in float32 and float64) in elementwise numpy only, so the rays' float32 inputs are the
same on every CPU.
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
CLEAR_MARGIN = 1e-3  # metres: a hit this far inside its face's edges and beyond the origin by Embree's own float32
# reckoning (a hundred times its rounding) is that face's for every CPU: where nothing else could name the ray (no
# other part's face overlaps it in its plane, no neighbouring pixel names a face it does not touch), it is decided
# without the float64 test, which would decide the same
RECAST_STEP = PLANE_GAP  # metres: a ray that passes its Embree face's edge is cast again from this far beyond it
RECASTS = 4  # at most this many times
FAR_MARGIN = 1e-4  # a shadow ray asks Embree for faces up to this much (relative, and metres) beyond its light


class ExactHits:
    """The first hits (and shadow rays' blockers) of rays decided in float64 among the faces that could be hit at
    Embree's hit point (see the module's text), so that the answer does not depend on which of them Embree's float32
    kernels reported.

    Faces are grouped by plane (unit normals within `PLANE_DECIMALS`, offsets within `PLANE_GAP` of the next); each
    face is described in its plane's two dominant axes, and a ray meets every face of a plane at one distance, the
    plane's. The candidates of a ray that Embree says hits face k: k; where the hit point lies within `EDGE_MARGIN`
    of k's edge, every face that shares a corner with k (`VERTEX_DECIMALS`) or k's plane; for the rays of an image,
    the faces its neighbouring pixels hit that touch neither k's corners nor its plane, with their corners' faces
    (`_around`); and of each candidate that holds the ray, the faces of other parts that overlap it in its plane
    (facing the same side, where it faces the ray).
    Of the candidates that contain their own hit point (2-D edge functions) in front of the origin: the nearest,
    then the one facing the ray, then the highest owner, then the lowest index. A ray none of whose candidates holds
    it passes its Embree face's edge: it is cast again from just beyond that face (`RayCaster`). A shadow ray is
    blocked where any candidate holds it before its light. Elementwise float64 arithmetic only
    (`monolib.data.exact`), so the answer is the CPU's only through the candidates Embree's hits name; a hit that is
    clear by Embree's own reckoning (`CLEAR_MARGIN`) and that nothing else could name is taken as it is, which the
    float64 test would also decide."""

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
        opposite = exact.norm(np.roll(V, -1, axis=1) - np.roll(V, 1, axis=1))  # (F, 3): the edge opposite corner i
        self.altitude = length[:, None] / np.maximum(opposite, 1e-300)  # corner i's distance to that edge
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
        # pairs of one plane, of two owners, whose boxes overlap by more than the tolerance: where a point inside one
        # face can lie inside the other; `same`: the two face the same side
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

    def _around(self, hit: np.ndarray, shape: tuple[int, int], pixels: np.ndarray, need: np.ndarray):
        """Candidate (ray, face) pairs from an image's neighbouring pixels: ray i is pixel `pixels[i]` of an image of
        `shape` (rows, columns); a ray whose 8 neighbouring pixels' rays hit a face that touches neither its own
        face's corners nor its plane (a silhouette, a seam, the sky's edge) takes that face and the faces of its
        corners. Pixels without a ray count as missed; only the rays of the mask `need` take pairs."""
        n_faces = len(self.owner)
        h, w = shape
        pixels = np.asarray(pixels, np.int32)
        at = pixels + 2 * (pixels // w) + (w + 3)  # in the image padded by one missed pixel
        grid = np.full((h + 2) * (w + 2), -1, np.int32)
        grid[at] = hit
        steps = np.array([dy * (w + 2) + dx for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx], np.int32)
        around = grid[at[need][:, None] + steps]
        own = np.asarray(hit)[need][:, None]
        r, c = np.nonzero((around >= 0) & (around != own))
        other = around[r, c].astype(np.int64)
        r = np.flatnonzero(need)[r]
        own = np.asarray(hit)[:, None]
        code = np.where(own[r, 0] >= 0, own[r, 0], 0) * n_faces + other
        at = np.minimum(np.searchsorted(self.neighbour_codes, code), len(self.neighbour_codes) - 1)
        foreign = (own[r, 0] < 0) | (self.neighbour_codes[at] != code)
        pair = np.unique(r[foreign] * n_faces + other[foreign])
        r, other = pair // n_faces, pair % n_faces
        rows = self.corners[other]
        return r[np.repeat(np.arange(len(r)), np.diff(rows.indptr))], rows.indices.astype(np.int64)

    def _before(self, r: np.ndarray, f: np.ndarray, o_all: np.ndarray, d_all: np.ndarray, limit: np.ndarray):
        """Of the (ray, face) pairs, those whose face's plane the ray meets between its origin and `limit` (per ray):
        a face beyond cannot be the one a ray meets first (nor block a shadow ray)."""
        t = (self.offset[f] - exact.dot(o_all[r], self.normal[f])) / exact.dot(d_all[r], self.normal[f])
        keep = (t > 0) & (t < limit[r])
        return r[keep], f[keep]

    def _hold(self, r: np.ndarray, f: np.ndarray, o_all: np.ndarray, d_all: np.ndarray):
        """Of the (ray, face) pairs, those whose face holds the ray's point on its plane in front of the origin:
        (ray, face, t)."""
        keep = self.valid[f]
        r, f = r[keep], f[keep]
        t, inside = self._inside(f, o_all[r], d_all[r])
        ok = (inside >= 0) & (t > 0)
        return r[ok], f[ok], t[ok]

    def _clear(self, hit: np.ndarray, embree: Optional[dict]) -> np.ndarray:
        """The rays whose Embree hit lies `CLEAR_MARGIN` inside its face's edges and beyond the origin, by Embree's
        own barycentric coordinates and distance (`embree`: its output; None: no ray)."""
        clear = np.zeros(len(hit), bool)
        if embree is None:
            return clear
        rays = np.flatnonzero(hit >= 0)
        u, v = embree["u"][rays].astype(np.float64), embree["v"][rays].astype(np.float64)
        edge = (np.stack([1.0 - u - v, u, v], axis=1) * self.altitude[hit[rays]]).min(axis=1)
        clear[rays] = (edge >= CLEAR_MARGIN) & (embree["tfar"][rays] > CLEAR_MARGIN)
        return clear

    def _containing(self, hit: np.ndarray, o_all: np.ndarray, d_all: np.ndarray, around: tuple, overlaps: bool,
                    skip: np.ndarray):
        """The candidates (see the class) of the rays not in `skip` (a mask) that contain their own hit point in
        front of the origin: (ray, face, t) sorted per ray by the decision's order (nearest, facing, highest owner,
        lowest index); and, for every ray, the distance (float64) to the plane of Embree's face (NaN where Embree
        hit nothing or the ray is skipped). `around`: the (ray, face) pairs of `_around`."""
        rays = np.flatnonzero((hit >= 0) & ~skip)
        k = hit[rays]
        t_k = np.full(len(hit), np.nan)
        t_k[rays], margin = self._inside(k, o_all[rays], d_all[rays])
        # candidate (ray, face) pairs: k itself; near k's edge, the faces of its corners and plane; the neighbouring
        # pixels' faces (`around`)
        near = np.flatnonzero(margin < EDGE_MARGIN)
        rows = self.neighbours[k[near]]
        ar, af = around
        r = np.concatenate([rays, rays[near][np.repeat(np.arange(len(near)), np.diff(rows.indptr))], ar[~skip[ar]]])
        f = np.concatenate([k, rows.indices.astype(np.int64), af[~skip[ar]]])
        r, f, t = self._hold(r, f, o_all, d_all)
        if overlaps:  # of each candidate that holds its ray, the faces of other parts overlapping it in its plane
            # (those facing the same side, where it faces the ray: one facing away never wins against it)
            facing = exact.dot(self.unit[f], d_all[r]) < 0
            pr, pf = [r], [f]
            for sel, table in ((np.flatnonzero(facing), self.overlap_same), (np.flatnonzero(~facing), self.overlap)):
                rows = table[f[sel]]
                pr.append(r[sel][np.repeat(np.arange(len(sel)), np.diff(rows.indptr))])
                pf.append(rows.indices.astype(np.int64))
            more = self._hold(np.concatenate(pr[1:]), np.concatenate(pf[1:]), o_all, d_all)
            r, f, t = (np.concatenate([a, b]) for a, b in zip((r, f, t), more))
        facing = exact.dot(self.unit[f], d_all[r]) < 0
        order = np.lexsort((f, -self.owner[f], ~facing, t, r))
        return r[order], f[order], t[order], t_k

    def _around_pairs(self, hit: np.ndarray, shape: Optional[tuple[int, int]], pixels: Optional[np.ndarray],
                      need: np.ndarray, o_all: np.ndarray, d_all: np.ndarray, limit: np.ndarray):
        """`_around`'s pairs of the rays `need`, kept where the face's plane lies before the ray's `limit`."""
        if shape is None:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        r, f = self._around(hit, shape, np.arange(len(hit)) if pixels is None else pixels, need)
        return self._before(r, f, o_all, d_all, limit)

    def resolve(self, hit: np.ndarray, origins: np.ndarray, dirs: np.ndarray,
                shape: Optional[tuple[int, int]] = None, pixels: Optional[np.ndarray] = None,
                embree: Optional[dict] = None):
        """`hit` (Embree's face index per ray, -1 for none) decided in float64 (see the class); rays in float64.
        `shape` (rows, columns): the rays are an image's, row by row (or, with `pixels`, ray i is pixel `pixels[i]`),
        and the faces their neighbouring pixels hit are candidates too (`_around`). `embree`: Embree's output for
        the rays (its u, v, tfar), which lets a clear hit (`_clear`) that nothing else could name be taken as it is.
        Returns the decided faces and the rays to cast again beyond their Embree face (none of whose candidates holds
        the ray: the ray passes its edge), with the distance to start from."""
        hit = np.asarray(hit)
        out = np.array(hit, copy=True)
        o_all = np.broadcast_to(np.asarray(origins, np.float64), np.shape(dirs))
        d_all = np.asarray(dirs, np.float64)
        clear = self._clear(hit, embree)
        # a clear hit holds its ray on every CPU: a face whose plane lies beyond it cannot be met first
        limit = np.where(clear, embree["tfar"] * (1 + FAR_MARGIN) + FAR_MARGIN if embree is not None else 0, np.inf)
        around = self._around_pairs(hit, shape, pixels, np.ones(len(hit), bool), o_all, d_all, limit)
        skip = clear.copy()
        skip[hit >= 0] &= np.diff(self.overlap.indptr)[hit[hit >= 0]] == 0
        skip[around[0]] = False
        r, f, _t, t_k = self._containing(hit, o_all, d_all, around, True, skip)
        best = np.r_[True, r[1:] != r[:-1]] if len(r) else np.zeros(0, bool)
        out[r[best]] = f[best]
        again = np.setdiff1d(np.flatnonzero((hit >= 0) & ~skip), r[best])
        out[again] = -1
        return out, again, t_k[again] + RECAST_STEP

    def blocked(self, hit: np.ndarray, origins: np.ndarray, dirs: np.ndarray, dists: np.ndarray,
                shape: Optional[tuple[int, int]] = None, pixels: Optional[np.ndarray] = None,
                embree: Optional[dict] = None):
        """Shadow rays: whether a face holds each ray (float64) before `dists`, among the candidates of `hit`
        (Embree's first face within a little more than `dists`; see `resolve`; a clear hit well before `dists`
        blocks as it is). Returns that, and the rays to cast again beyond their Embree face (rejected, and nearer
        than `dists`), with the distance to start from."""
        hit = np.asarray(hit)
        o_all = np.broadcast_to(np.asarray(origins, np.float64), np.shape(dirs))
        d_all = np.asarray(dirs, np.float64)
        dists = np.asarray(dists, np.float64)
        skip = self._clear(hit, embree)
        if embree is not None:
            skip &= embree["tfar"] < dists * (1 - FAR_MARGIN) - FAR_MARGIN
        limit = dists * (1 + FAR_MARGIN) + FAR_MARGIN
        around = self._around_pairs(hit, shape, pixels, ~skip, o_all, d_all, limit)
        r, _f, t, t_k = self._containing(hit, o_all, d_all, around, False, skip)
        out = skip.copy()
        out[r[t < dists[r]]] = True
        again = np.flatnonzero((hit >= 0) & ~out & (t_k < dists))
        return out, again, t_k[again] + RECAST_STEP


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

    def _embree_first(self, origins: np.ndarray, dirs: np.ndarray, dists: Optional[np.ndarray] = None,
                      output: bool = False):
        """Embree's first face along each ray (within `dists`, if given), or -1 (`output`: Embree's whole output,
        with the hits' u, v and distance tfar). The origins are rounded to float32 first; the directions to float32
        and normalised again (float64 norm of the float32 squares)."""
        o = np.asarray(origins, dtype=np.float32)
        d = np.asarray(dirs, dtype=np.float32)
        sq = d * d
        norm = np.sqrt(sq[:, 0].astype(np.float64) + sq[:, 1] + sq[:, 2])
        unit = d * np.where(norm > 1e-12, 1.0 / norm, norm)[:, None]
        far = None if dists is None else np.asarray(dists).astype(np.float32)
        return self.scene.run(self._origins(o), unit.astype(np.float32), dists=far, output=output)

    def first(self, origins: np.ndarray, dirs: np.ndarray, shape: Optional[tuple[int, int]] = None,
              pixels: Optional[np.ndarray] = None) -> np.ndarray:
        """Index of the first triangle each ray hits, or -1 (`_embree_first`; decided by `ExactHits` when the caster
        has one: a ray that passes its Embree face's edge is cast again from beyond it). `shape`: the rays are an
        image's (rows, columns), row by row, or with `pixels` ray i is pixel `pixels[i]`; `ExactHits` reads them."""
        if self.exact is None:
            return self._embree_first(origins, dirs)
        o = np.broadcast_to(np.asarray(origins, np.float64), np.shape(dirs))
        d = np.asarray(dirs, np.float64)
        res = self._embree_first(o, d, output=True)
        out, again, start = self.exact.resolve(res["primID"], o, d, shape, pixels, res)
        for _ in range(RECASTS):
            if not len(again):
                break
            o2 = o[again] + d[again] * start[:, None]
            decided, more, start = self.exact.resolve(self._embree_first(o2, d[again]), o2, d[again])
            out[again] = decided
            again = again[more]
        return out

    def occluded(self, origins: np.ndarray, dirs: np.ndarray, dists: np.ndarray,
                 shape: Optional[tuple[int, int]] = None, pixels: Optional[np.ndarray] = None) -> np.ndarray:
        """Whether something lies along each ray before `dists` (shadow rays; unit directions). Without `ExactHits`,
        Embree's occlusion query; with it, Embree's first face within a little more than `dists`, decided in float64
        (`ExactHits.blocked`; `shape` and `pixels` as in `first`), and cast again beyond a face the ray passes."""
        if self.exact is None:
            res = self.scene.run(self._origins(origins), np.asarray(dirs).astype(np.float32),
                                 dists=np.asarray(dists).astype(np.float32), query="OCCLUDED")
            return res != -1
        o = np.broadcast_to(np.asarray(origins, np.float64), np.shape(dirs))
        d = np.asarray(dirs, np.float64)
        dists = np.asarray(dists, np.float64)
        res = self._embree_first(o, d, dists * (1 + FAR_MARGIN) + FAR_MARGIN, output=True)
        out, again, start = self.exact.blocked(res["primID"], o, d, dists, shape, pixels, res)
        for _ in range(RECASTS):
            if not len(again):
                break
            o2 = o[again] + d[again] * start[:, None]
            rest = dists[again] - start
            hit2 = self._embree_first(o2, d[again], rest * (1 + FAR_MARGIN) + FAR_MARGIN)
            decided, more, start = self.exact.blocked(hit2, o2, d[again], rest)
            out[again] = decided
            again = again[more]
        return out
