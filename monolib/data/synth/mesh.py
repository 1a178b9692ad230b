"""The triangle mesh of one setting (`build_mesh`): floor, ceiling, walls with their doors, windows, blinds and
curtains, and the furniture of the layout, each part with its NYU40 class, instance, render entity and material."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from monolib.data import exact
from monolib.data.labels import ID
from monolib.data.synth.furniture import _box, _cyl
from monolib.data.synth.rooms import WALL_T, Family, Layout, _rot, _wall_frame, house_box


@dataclass
class SceneMesh:
    vertices: np.ndarray
    faces: np.ndarray
    face_part: np.ndarray  # part index per face
    part_sem: np.ndarray  # NYU40 id per part
    part_inst: np.ndarray  # instance id per part (>= 1)
    part_entity: np.ndarray  # render entity id per part (>= 1)
    part_mat: np.ndarray  # material index per part
    part_inv: np.ndarray  # (P, 4, 4) world -> part-local (for textures)
    materials: list
    instances: list  # (instance id, NYU40 id, name)


def _wall_pieces(L: float, H: float, holes: list) -> list:
    """Rectangles (s0, s1, z0, z1) covering [0, L] x [0, H] minus the given holes."""
    cuts = sorted({0.0, L, *[h[0] for h in holes], *[h[1] for h in holes]})
    out = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        if b - a < 1e-6:
            continue
        mid = (a + b) / 2
        zs = sorted((h[2], h[3]) for h in holes if h[0] <= mid <= h[1])
        z = 0.0
        for z0, z1 in zs:
            if z0 > z:
                out.append((a, b, z, z0))
            z = max(z, z1)
        if z < H:
            out.append((a, b, z, H))
    return out


def build_mesh(fam: Family, lay: Layout, seed: int, setting_index: int) -> SceneMesh:
    rng = np.random.default_rng([seed, 15485863, setting_index])
    mat_names = sorted(fam.materials)
    mat_index = {k: i for i, k in enumerate(mat_names)}
    materials = [fam.materials[k] for k in mat_names]

    V, F, FP = [], [], []
    psem, pinst, pmat, pinv = [], [], [], []
    instances = []
    nv = 0

    def add_obj(sem: int, parts: list, T: np.ndarray, name: str):
        """One instance (`sem` -1: unlabelled geometry, instance -1, as Hypersim's outside)."""
        nonlocal nv
        if sem >= 1:
            inst = len(instances) + 1
            instances.append((inst, sem, name))
        else:
            inst = -1
        inv = exact.rigid_inverse(T)
        for (v, f), mk in parts:
            vw = exact.matmul(v, T[:3, :3].T) + T[:3, 3]
            pidx = len(psem)
            V.append(vw)
            F.append(f + nv)
            FP.append(np.full(len(f), pidx))
            nv += len(v)
            psem.append(sem)
            pinst.append(inst)
            pmat.append(mat_index[mk])
            pinv.append(inv)

    W, D, H = lay.W, lay.D, lay.H
    _room(add_obj, rng, fam, W, D, H, lay.openings, np.eye(4), range(4), fam.wall_key)
    if lay.annex is not None:
        a = lay.annex
        T = np.eye(4)
        T[:3, :3] = _rot(a["yaw"])
        T[:2, 3] = a["origin"]
        _room(add_obj, rng, fam, a["W"], a["D"], H, a["openings"], T, (1, 2, 3), ["wall"] * 4)
    _outside(add_obj, fam, house_box(fam))
    # furniture
    for it in lay.items:
        T = np.eye(4)
        T[:3, :3] = _rot(it.yaw)
        T[:3, 3] = (it.x, it.y, it.z0)
        for ob in it.objs:
            name = [k for k, v in ID.items() if v == ob.sem][0]
            add_obj(ob.sem, ob.parts, T, name)
    vertices = np.concatenate(V)
    faces = np.concatenate(F).astype(np.int64)
    npart = len(psem)
    ent = np.arange(1, npart + 1)
    return SceneMesh(vertices, faces, np.concatenate(FP), np.array(psem, np.int16), np.array(pinst, np.int16),
                     ent.astype(np.int16), np.array(pmat), np.stack(pinv), materials, instances)


def _room(add_obj, rng: np.random.Generator, fam: Family, W: float, D: float, H: float, openings: list,
          T_room: np.ndarray, walls, wall_key: list) -> None:
    """Floor, ceiling and the walls `walls` of a W x D room (in its frame `T_room`) with holes for its doors,
    windows and openings; door leaves, window frames, blinds and curtains. A window is an opening: it shows what
    is outside."""
    add_obj(ID["floor"], [(_box((-0.2, -0.2, -0.1), (W + 0.2, D + 0.2, 0.0)), "floor")], T_room, "floor")
    add_obj(ID["ceiling"], [(_box((-0.2, -0.2, H), (W + 0.2, D + 0.2, H + 0.1)), "ceiling")], T_room, "ceiling")
    # walls with holes; local wall frame: x along wall, y into the room, z up
    for w in walls:
        o, t, nrm, L = _wall_frame(w, W, D)
        T = np.eye(4)
        T[:3, :3] = _rot(w * math.pi / 2)
        T[:2, 3] = o
        T = exact.matmul(T_room, T)
        holes = [(a, b, z0, z1) for (ww, a, b, z0, z1, k) in openings if ww == w]
        pieces = _wall_pieces(L, H, holes)
        parts = [(_box((s0, -WALL_T, z0), (s1, 0.0, z1)), wall_key[w]) for s0, s1, z0, z1 in pieces]
        add_obj(ID["wall"], parts, T, f"wall{w}")
        if fam.skirting:  # skirting boards where the wall meets the floor
            add_obj(ID["otherstructure"], [(_box((s0, 0.0, 0.0), (s1, 0.015, 0.1)), "skirting")
                                           for s0, s1, z0, z1 in pieces if z0 == 0.0], T, "skirting")
        for (ww, a, b, z0, z1, k) in openings:
            if ww != w or k == "opening":  # an opening to the next room: the hole alone
                continue
            if k == "door":  # closed: what is behind a door is not built
                leaf = _box((a + 0.02, -0.06, 0.0), (b - 0.02, -0.02, z1 - 0.02))
                frame = [(_box((a - 0.06, -WALL_T - 0.01, 0), (a, 0.02, z1 + 0.06)), "frame"),
                         (_box((b, -WALL_T - 0.01, 0), (b + 0.06, 0.02, z1 + 0.06)), "frame"),
                         (_box((a - 0.06, -WALL_T - 0.01, z1), (b + 0.06, 0.02, z1 + 0.06)), "frame")]
                knob = _box((b - 0.12, -0.02, 1.0), (b - 0.08, 0.04, 1.04))
                add_obj(ID["door"], [(leaf, "door"), (knob, "metal")] + frame, T, "door")
            else:
                parts = [(_box((a - 0.05, -WALL_T - 0.01, z0 - 0.05), (a, 0.02, z1 + 0.05)), "frame"),
                         (_box((b, -WALL_T - 0.01, z0 - 0.05), (b + 0.05, 0.02, z1 + 0.05)), "frame"),
                         (_box((a - 0.05, -WALL_T - 0.01, z1), (b + 0.05, 0.02, z1 + 0.05)), "frame"),
                         (_box((a - 0.08, -WALL_T - 0.01, z0 - 0.05), (b + 0.08, 0.05, z0)), "frame"),
                         (_box(((a + b) / 2 - 0.02, -0.08, z0), ((a + b) / 2 + 0.02, -0.05, z1)), "frame")]
                add_obj(ID["window"], parts, T, "window")
                r = rng.uniform()
                if r < 0.1:  # blinds: slats over the upper part
                    zb = rng.uniform((z0 + z1) / 2, z1)
                    slats = [(_box((a, 0.03, z), (b, 0.05, z + 0.035)), "frame")
                             for z in np.arange(zb, z1 - 0.03, 0.05)]
                    if slats:
                        add_obj(ID["blinds"], slats, T, "blinds")
                elif r < 0.3:  # curtains on both sides
                    for side in (-1, 1):
                        cw = rng.uniform(0.3, 0.5)
                        x0 = a - 0.15 if side < 0 else b + 0.15 - cw
                        add_obj(ID["curtain"], [(_box((x0, 0.04, 0.1 if z0 > 0.9 else max(0.02, z0 - 0.2)),
                                                      (x0 + cw, 0.1, min(H - 0.05, z1 + 0.25))), "curtain")], T,
                                "curtain")


def _outside(add_obj, fam: Family, box: tuple) -> None:
    """The ground around the house, the facades and trees of the family's `outside` (unlabelled, as Hypersim's
    exteriors mostly are)."""
    x0, y0, x1, y1 = box
    I4 = np.eye(4)
    ground = fam.outside[0][1]
    add_obj(-1, [(_box((x0 - 150, y0 - 150, ground - 0.1), (x1 + 150, y1 + 150, ground)), "ground")], I4, "ground")
    if ground < -0.5:  # a flat: the building it is in, below its floor
        add_obj(-1, [(_box((x0 - 0.5, y0 - 0.5, ground), (x1 + 0.5, y1 + 0.5, -0.1)), "facade0")], I4, "building")
    for thing in fam.outside[1:]:
        if thing[0] == "building":
            _k, x, y, w, d, top, m = thing
            add_obj(-1, [(_box((x - w / 2, y - d / 2, ground), (x + w / 2, y + d / 2, top)), f"facade{m}")], I4,
                    "building")
        else:
            _k, x, y, r, h = thing
            add_obj(-1, [(_cyl(x, y, ground, 0.2, h * 0.45, 6), "bark"),
                         (_cyl(x, y, ground + h * 0.35, r, h * 0.65, 8), "leaves")], I4, "tree")
