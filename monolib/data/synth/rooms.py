"""Rooms of the mini-Hypersim: the room types, a *family* (`make_family`: room size, the furniture catalogue, the
materials and lights that its settings share) and the *layout* of one setting (`make_layout`: doors and windows,
the furniture placed against walls, on walls and on the floor, small props, chairs and lights)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from monolib.data.labels import ID
from monolib.data.synth.furniture import CATALOGUE, MOUNT_Z, Item, Obj, _bx, _cyl, b_chair, b_desk, w_picture
from monolib.data.synth.materials import N_PROP_MATERIALS, _family_materials


ROOM_TYPES = ["office", "bedroom", "living room", "kitchen", "bathroom", "classroom", "dining room", "library"]
SCENE_TYPE_LABEL = {"office": "Office", "bedroom": "Bedroom", "living room": "Living room", "kitchen": "Kitchen",
                    "bathroom": "Bathroom", "classroom": "Classroom", "dining room": "Dining room",
                    "library": "Library"}


# room type -> [(kind, min count, max count, probability the family has it)]
ROOMS = {
    "office": [("desk", 1, 3, 1.0), ("chair", 0, 0, 1.0), ("bookshelf", 1, 2, 0.9), ("cabinet", 1, 2, 0.8),
               ("whiteboard", 1, 1, 0.6), ("picture", 1, 2, 0.7), ("boxes", 1, 2, 0.6), ("floorlamp", 1, 1, 0.5),
               ("shelves", 1, 1, 0.5), ("table", 1, 1, 0.4), ("otherfurniture", 1, 1, 0.4), ("floormat", 1, 1, 0.3),
               ("plant", 1, 2, 0.6), ("lounge_chair", 1, 1, 0.3)],
    "bedroom": [("bed", 1, 1, 1.0), ("nightstand", 1, 2, 1.0), ("dresser", 1, 1, 0.8), ("wardrobe", 1, 1, 0.6),
                ("picture", 1, 3, 0.9), ("floormat", 1, 1, 0.6), ("mirror", 1, 1, 0.5), ("desk", 1, 1, 0.4),
                ("chair", 0, 0, 1.0), ("boxes", 1, 1, 0.3), ("floorlamp", 1, 1, 0.4), ("shelves", 1, 1, 0.4),
                ("plant", 1, 1, 0.5), ("lounge_chair", 1, 1, 0.5)],
    "living room": [("sofa", 1, 1, 1.0), ("coffee_table", 1, 1, 0.9), ("tvstand", 1, 1, 0.8), ("armchair", 1, 2, 0.5),
                    ("bookshelf", 1, 1, 0.6), ("picture", 1, 3, 0.9), ("floormat", 1, 1, 0.8), ("floorlamp", 1, 2, 0.8),
                    ("cabinet", 1, 1, 0.4), ("shelves", 1, 1, 0.4), ("otherfurniture", 1, 1, 0.4),
                    ("plant", 1, 2, 0.7), ("side_table", 1, 2, 0.7), ("lounge_chair", 1, 2, 0.7)],
    "kitchen": [("counter", 1, 2, 1.0), ("kitchen_sink", 1, 1, 1.0), ("fridge", 1, 1, 1.0), ("upper_cabinet", 1, 2, 0.8),
                ("table", 1, 1, 0.7), ("chair", 0, 0, 1.0), ("picture", 1, 1, 0.4), ("boxes", 1, 1, 0.3),
                ("shelves", 1, 1, 0.4), ("cabinet", 1, 1, 0.5), ("floormat", 1, 1, 0.3), ("plant", 1, 1, 0.4)],
    "bathroom": [("toilet", 1, 1, 1.0), ("vanity", 1, 1, 1.0), ("mirror", 1, 1, 1.0), ("bathtub", 1, 1, 0.7),
                 ("towel", 1, 2, 0.9), ("floormat", 1, 1, 0.6), ("cabinet", 1, 1, 0.5), ("shelves", 1, 1, 0.5),
                 ("picture", 1, 1, 0.3), ("plant", 1, 1, 0.4)],
    "classroom": [("student_desk", 4, 9, 1.0), ("chair", 0, 0, 1.0), ("whiteboard", 1, 1, 1.0), ("desk", 1, 1, 1.0),
                  ("bookshelf", 1, 2, 0.6), ("cabinet", 1, 2, 0.6), ("picture", 1, 2, 0.5), ("boxes", 1, 1, 0.4),
                  ("plant", 1, 1, 0.4)],
    "dining room": [("dining_table", 1, 1, 1.0), ("chair", 0, 0, 1.0), ("cabinet", 1, 2, 0.8), ("picture", 1, 3, 0.9),
                    ("floorlamp", 1, 1, 0.5), ("otherfurniture", 1, 1, 0.5), ("floormat", 1, 1, 0.4),
                    ("shelves", 1, 1, 0.4), ("plant", 1, 2, 0.6), ("side_table", 1, 1, 0.4)],
    "library": [("bookshelf", 3, 6, 1.0), ("table", 1, 2, 1.0), ("chair", 0, 0, 1.0), ("armchair", 1, 1, 0.5),
                ("floorlamp", 1, 2, 0.6), ("picture", 1, 1, 0.5), ("floormat", 1, 1, 0.5), ("desk", 1, 1, 0.4),
                ("plant", 1, 1, 0.5), ("lounge_chair", 1, 2, 0.5)],
}
# surfaces that carry small props (vases, bottles, bowls, books, paper) and table lamps: kind -> (props, lamp chance)
SURFACES = {"table": (2, 0.1), "dining_table": (3, 0.0), "coffee_table": (2, 0.0), "desk": (2, 0.6),
            "student_desk": (1, 0.0), "nightstand": (1, 0.0), "dresser": (3, 0.5), "counter": (3, 0.1),
            "cabinet": (2, 0.2), "otherfurniture": (2, 0.5), "side_table": (1, 0.8), "shelves": (2, 0.0),
            "vanity": (1, 0.0), "bookshelf": (1, 0.0)}
ROOM_SIZE = {"bathroom": ((2.6, 2.4), (4.0, 3.5)), "kitchen": ((3.2, 3.0), (5.5, 4.5)),
             "classroom": ((5.5, 5.0), (8.0, 7.0)), "library": ((4.5, 4.0), (7.5, 6.5))}


@dataclass
class Family:
    index: int
    room: str
    size: tuple  # W, D, H
    materials: dict
    items: list  # (kind, dims (w, d, h), extra dict)
    wall_key: list  # wall material key per wall
    temp: float = 0.5
    n_lights: int = 2  # ceiling fixtures (dim settings: one)
    window_level: float = 2.0  # daylight through the windows (dim settings: dusk)
    glass: bool = True  # windows glazed (else open: rays escape, invalid pixels)
    skirting: bool = False  # skirting boards along the walls (NYU40 otherstructure)
    pendant: float = 0.0  # how far the ceiling lamps hang below the ceiling (m; 0: flush)
    clutter: float = 0.6  # how many small props stand on the family's surfaces (0..1)


def make_family(seed: int, index: int, room: str) -> Family:
    rng = np.random.default_rng([seed, 7919, index])
    lo, hi = ROOM_SIZE.get(room, ((3.2, 3.0), (6.0, 5.0)))
    W, D = rng.uniform(lo[0], hi[0]), rng.uniform(lo[1], hi[1])
    H = rng.uniform(2.5, 3.2)
    mats = _family_materials(rng, room)
    temp = float(rng.uniform(0.2, 0.8))  # light colour temperature of the family's fixtures (0 warm .. 1 cool)
    items = []
    pic = 0
    for kind, nmin, nmax, p in ROOMS[room]:
        if kind == "chair" or rng.uniform() > p:
            continue
        n = int(rng.integers(nmin, nmax + 1))
        lo_d, hi_d = CATALOGUE[kind][2]
        dims = tuple(float(rng.uniform(a, b)) for a, b in zip(lo_d, hi_d))
        for _ in range(n):
            extra = {}
            if kind == "picture":
                extra["mat"] = f"picture{pic % 3}"
                pic += 1
                dims = tuple(float(rng.uniform(a, b)) for a, b in zip(lo_d, hi_d))
            items.append((kind, dims, extra))
    chair_dims = tuple(float(rng.uniform(a, b)) for a, b in zip(*CATALOGUE["chair"][2]))
    items.append(("chair", chair_dims, {}))  # the family's chair model (the layout decides how many)
    wall_key = ["wall"] * 4
    if rng.uniform() < 0.5:
        wall_key[int(rng.integers(4))] = "wall2"
    return Family(index, room, (W, D, H), mats, items, wall_key, temp, int(rng.integers(1, 4)),
                  float(rng.uniform(2.5, 6.0)), bool(rng.uniform() < 0.85), skirting=bool(rng.uniform() < 0.5),
                  pendant=float(rng.uniform(0.3, 0.9)) if rng.uniform() < 0.5 else 0.0,
                  clutter=float(rng.uniform(0.3, 1.0)))


# ---- the layout of one setting ---------------------------------------------------------------------------------

def _props_on(it: Item, fam: Family, rng: np.random.Generator) -> list:
    """Small things on the top of `it` (item-local frame): vases, bottles, bowls (otherprop), a stack of books, a
    sheet of paper, sometimes a table lamp. How many follows the family's clutter level."""
    n_max, p_lamp = SURFACES[it.kind]
    top = it.h
    objs = []
    if it.kind not in ("nightstand",) and rng.uniform() < p_lamp:  # nightstands already carry their lamp
        x, y = rng.uniform(-0.35, 0.35) * it.w, rng.uniform(-0.2, 0.2) * it.d
        objs.append(Obj(ID["lamp"], [(_cyl(x, y, top, 0.07, 0.03), "metal"), (_cyl(x, y, top + 0.03, 0.012, 0.22), "metal"),
                                     (_cyl(x, y, top + 0.2, 0.13, 0.18), "shade")]))
    n = int(rng.binomial(n_max, fam.clutter))
    for _ in range(n):
        x, y = rng.uniform(-0.4, 0.4) * it.w, rng.uniform(-0.3, 0.3) * it.d
        kind = rng.choice(["vase", "bottle", "bowl", "books", "paper"], p=[0.35, 0.25, 0.25, 0.1, 0.05])
        mat = f"prop{int(rng.integers(N_PROP_MATERIALS))}"
        if kind == "vase":
            objs.append(Obj(ID["otherprop"], [(_cyl(x, y, top, rng.uniform(0.05, 0.09), rng.uniform(0.15, 0.35), 10), mat)]))
        elif kind == "bottle":
            objs.append(Obj(ID["otherprop"], [(_cyl(x, y, top, 0.035, rng.uniform(0.2, 0.32), 8), mat)]))
        elif kind == "bowl":
            objs.append(Obj(ID["otherprop"], [(_cyl(x, y, top, rng.uniform(0.1, 0.16), 0.07, 12), mat)]))
        elif kind == "books":
            objs.append(Obj(ID["books"], [(_bx(x, y, top, 0.22, 0.16, rng.uniform(0.06, 0.15)), "books")]))
        else:
            objs.append(Obj(ID["paper"], [(_bx(x, y, top, 0.3, 0.22, 0.005), "paper")]))
    return objs


def _rot(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


@dataclass
class Layout:
    W: float
    D: float
    H: float
    items: list  # Item
    rects: list  # (xmin, ymin, xmax, ymax) floor footprints (obstacles)
    lights: list  # (position (3,), rgb (3,))
    ambient: np.ndarray
    window_emission: np.ndarray
    openings: list = field(default_factory=list)  # (wall, s0, s1, z0, z1, kind)


def _wall_frame(w: int, W: float, D: float):
    """(origin (x, y), direction along the wall, inward normal, length) of wall w (0: y=0, 1: x=W, 2: y=D, 3: x=0)."""
    if w == 0:
        return np.array([0.0, 0.0]), np.array([1.0, 0.0]), np.array([0.0, 1.0]), W
    if w == 1:
        return np.array([W, 0.0]), np.array([0.0, 1.0]), np.array([-1.0, 0.0]), D
    if w == 2:
        return np.array([W, D]), np.array([-1.0, 0.0]), np.array([0.0, -1.0]), W
    return np.array([0.0, D]), np.array([0.0, -1.0]), np.array([1.0, 0.0]), D


def _footprint(x, y, yaw, w, d):
    c, s = abs(math.cos(yaw)), abs(math.sin(yaw))
    hx, hy = (w * c + d * s) / 2, (w * s + d * c) / 2
    return (x - hx, y - hy, x + hx, y + hy)


def _overlaps(r, rects, pad=0.05):
    for q in rects:
        if r[0] < q[2] + pad and q[0] < r[2] + pad and r[1] < q[3] + pad and q[1] < r[3] + pad:
            return True
    return False


@dataclass
class _Draft:
    """A layout in progress: the room, the setting's random numbers and what is placed so far."""
    W: float
    D: float
    H: float
    rng: np.random.Generator
    items: list = field(default_factory=list)  # Item
    rects: list = field(default_factory=list)  # floor footprints taken (obstacles)
    high_rects: list = field(default_factory=list)  # footprints of high wall units
    wall_used: dict = field(default_factory=lambda: {w: [] for w in range(4)})  # intervals along each wall taken
    openings: list = field(default_factory=list)  # (wall, s0, s1, z0, z1, kind)
    chair_anchors: list = field(default_factory=list)  # (item, "front1": one chair in front | "around": a table)


def make_layout(fam: Family, seed: int, setting_index: int, dim: bool) -> Layout:
    """One setting of a family, step by step: the family's doors and windows, the furniture (classroom rows of
    desks, then the family's items from the largest footprint down: against a wall, mounted on a wall, or free on
    the floor), small props on the surfaces, chairs at the desks and tables, and the lights. The steps draw from
    one generator of the setting in this order."""
    W, D, H = fam.size
    draft = _Draft(W, D, H, np.random.default_rng([seed, 104729, setting_index]))
    _place_openings(draft, fam, np.random.default_rng([seed, 7919, fam.index, 1]))  # shared by the family
    furniture = [it for it in fam.items if it[0] != "chair"]
    order = sorted(range(len(furniture)), key=lambda i: -furniture[i][1][0] * furniture[i][1][1])
    _place_desk_rows(draft, [furniture[i] for i in order if CATALOGUE[furniture[i][0]][1] == "grid"])
    for i in order:
        _place_furniture(draft, *furniture[i])
    _place_props(draft, fam)
    _place_chairs(draft, [it[1] for it in fam.items if it[0] == "chair"][0])
    lights, ambient, window_emission = _place_lights(draft, fam, seed, dim)
    return Layout(W, D, H, draft.items, draft.rects, lights, ambient, window_emission, draft.openings)


def _place_openings(draft: _Draft, fam: Family, orng: np.random.Generator) -> None:
    """Doors (their swing kept free on the floor) and windows on the walls, from the family's generator `orng`."""
    W, D, H = draft.W, draft.D, draft.H
    n_doors = 1 + int(orng.uniform() < 0.25)
    n_windows = int(orng.integers(0 if fam.room == "bathroom" else 1, 3 if min(W, D) > 3.5 else 2))
    for kind, n in (("door", n_doors), ("window", n_windows)):
        for _ in range(n):
            for _try in range(30):
                w = int(orng.integers(4))
                o, t, nrm, L = _wall_frame(w, W, D)
                ow = orng.uniform(0.8, 0.95) if kind == "door" else orng.uniform(0.9, min(2.2, L - 0.8))
                s0 = orng.uniform(0.3, L - ow - 0.3) if L - ow - 0.6 > 0 else None
                if s0 is None or any(s0 < b + 0.2 and a < s0 + ow + 0.2 for a, b in draft.wall_used[w]):
                    continue
                draft.wall_used[w].append((s0, s0 + ow))
                if kind == "door":
                    z0, z1 = 0.0, 2.05
                    c = o + t * (s0 + ow / 2) + nrm * 0.5
                    draft.rects.append(_footprint(c[0], c[1], w * math.pi / 2, ow + 0.2, 1.0))  # keep the swing free
                else:
                    z0 = orng.uniform(0.8, 1.0)
                    z1 = min(H - 0.25, z0 + orng.uniform(1.1, 1.6))
                draft.openings.append((w, s0, s0 + ow, z0, z1, kind))
                break


def _clear_of_openings(draft: _Draft, w: int, s0: float, s1: float, z0: float, z1: float) -> bool:
    """Whether the span [s0, s1] x [z0, z1] of wall w keeps clear of its doors and windows."""
    for (ww, a, b, oz0, oz1, _k) in draft.openings:
        if ww == w and s0 < b + 0.1 and a < s1 + 0.1 and z0 < oz1 and oz0 < z1:
            return False
    return True


def _place_desk_rows(draft: _Draft, grid_items: list) -> None:
    """Classroom: rows of student desks facing the whiteboard wall (wall 0, -y), a chair in front of each."""
    if not grid_items:
        return
    rng, W, D = draft.rng, draft.W, draft.D
    dims = grid_items[0][1]
    n = len(grid_items)
    cols = max(1, int((W - 1.6) // (dims[0] + 0.5)))
    yaw0 = math.pi  # face wall 0 (-y)
    jitter = rng.uniform(-0.3, 0.3, 2)
    for k in range(n):
        r_, c_ = divmod(k, cols)
        x = 0.8 + dims[0] / 2 + c_ * (dims[0] + 0.5) + jitter[0] + rng.uniform(-0.08, 0.08)
        y = 2.4 + r_ * (dims[1] + 0.9) + jitter[1]
        fp = _footprint(x, y, yaw0, dims[0], dims[1])
        if fp[2] > W - 0.4 or fp[3] > D - 0.6 or fp[0] < 0.3 or _overlaps(fp, draft.rects):
            continue
        it = Item("student_desk", b_desk(dims, {}), *dims, x=x, y=y, yaw=yaw0 + rng.normal(0, 0.04))
        draft.items.append(it)
        draft.rects.append(fp)
        draft.chair_anchors.append((it, "front1"))


def _place_furniture(draft: _Draft, kind: str, dims: tuple, extra: dict) -> None:
    """One of the family's items, placed the way its catalogue entry says (grid items are `_place_desk_rows`')."""
    how = CATALOGUE[kind][1]
    if how in ("wall", "wall_high"):
        it = _place_against_wall(draft, kind, dims, high=(how == "wall_high"))
    elif how == "mount":
        it = _mount_on_wall(draft, kind, dims)
    elif how in ("centre", "free", "corner", "floor"):
        it = _place_on_floor(draft, kind, dims, how)
    else:
        it = None
    if it is not None:
        it.objs = CATALOGUE[kind][0](dims, {}) if kind != "picture" else w_picture(dims, {}, extra["mat"])
        draft.items.append(it)


def _place_against_wall(draft: _Draft, kind: str, dims: tuple, high: bool = False) -> Optional[Item]:
    """A unit standing against a wall (`high`: hung above the floor, 1.3-1.7 m), clear of the doors and windows
    and of the floor footprints (`high`: of the other high units); a desk gets a chair anchor."""
    rng, W, D, H = draft.rng, draft.W, draft.D, draft.H
    w_, d_, h_ = dims
    for _try in range(60):
        w = int(rng.integers(4))
        o, t, nrm, L = _wall_frame(w, W, D)
        if L < w_ + 0.1:
            continue
        s = rng.uniform(w_ / 2 + 0.05, L - w_ / 2 - 0.05)
        z0 = 0.0 if not high else rng.uniform(1.3, min(1.7, H - h_ - 0.1))
        if not _clear_of_openings(draft, w, s - w_ / 2, s + w_ / 2, z0, z0 + h_):
            continue
        c = o + t * s + nrm * (d_ / 2 + 0.02)
        yaw = w * math.pi / 2
        fp = _footprint(c[0], c[1], yaw, w_, d_)
        if _overlaps(fp, draft.high_rects if high else draft.rects):
            continue
        it = Item(kind, [], w_, d_, h_, float(c[0]), float(c[1]), yaw, z0)
        (draft.high_rects if high else draft.rects).append(fp)
        if kind == "desk":
            draft.chair_anchors.append((it, "front1"))
        return it
    return None


def _mount_on_wall(draft: _Draft, kind: str, dims: tuple) -> Optional[Item]:
    """A flat thing on a wall (picture, whiteboard, mirror, towel) at its catalogue height, clear of the doors and
    windows, of other mounted things and of the furniture in front of it."""
    rng, W, D, H = draft.rng, draft.W, draft.D, draft.H
    zlo, zhi = MOUNT_Z[kind]
    for _try in range(60):
        w = int(rng.integers(4))
        o, t, nrm, L = _wall_frame(w, W, D)
        if L < dims[0] + 0.2:
            continue
        s = rng.uniform(dims[0] / 2 + 0.1, L - dims[0] / 2 - 0.1)
        z0 = rng.uniform(zlo, zhi)
        if z0 + dims[2] > H - 0.1 or not _clear_of_openings(draft, w, s - dims[0] / 2, s + dims[0] / 2, z0,
                                                            z0 + dims[2]):
            continue
        if any(a < s + dims[0] / 2 + 0.1 and s - dims[0] / 2 < b + 0.1 for a, b in draft.wall_used[w]):
            continue
        # not behind tall furniture
        c = o + t * s + nrm * 0.05
        fp = _footprint(c[0], c[1], w * math.pi / 2, dims[0], 0.1)
        tall = [_footprint(q.x, q.y, q.yaw, q.w, q.d) for q in draft.items if q.h > z0 - 0.05]
        if _overlaps(fp, tall, pad=0.0) or _overlaps(fp, draft.high_rects, pad=0.0):
            continue
        draft.wall_used[w].append((s - dims[0] / 2, s + dims[0] / 2))
        return Item(kind, [], *dims, x=float(c[0] - nrm[0] * 0.05), y=float(c[1] - nrm[1] * 0.05),
                    yaw=w * math.pi / 2, z0=z0)
    return None


def _place_on_floor(draft: _Draft, kind: str, dims: tuple, how: str) -> Optional[Item]:
    """A free-standing piece: ``centre`` (kept well away from the rest), ``free`` (an armchair facing the room
    centre), ``corner``, or ``floor`` (a floor mat: under the furniture, never on another mat). Tables get chair
    anchors around them."""
    rng, W, D = draft.rng, draft.W, draft.D
    for _try in range(80):
        if how == "corner":
            cx = rng.choice([0.35, W - 0.35])
            cy = rng.choice([0.35, D - 0.35])
            yaw = 0.0
        else:
            m = 0.9 if how == "centre" else 0.6
            cx, cy = rng.uniform(m, W - m), rng.uniform(m, D - m)
            yaw = (rng.integers(4) * math.pi / 2 if how != "free" else rng.uniform(0, 2 * math.pi))
            yaw += rng.normal(0, 0.05)
        fp = _footprint(cx, cy, yaw, dims[0], dims[1])
        if fp[0] < 0.05 or fp[1] < 0.05 or fp[2] > W - 0.05 or fp[3] > D - 0.05:
            continue
        if how != "floor" and _overlaps(fp, draft.rects, pad=0.5 if how == "centre" else 0.15):
            continue
        if how == "floor" and _overlaps(fp, [_footprint(q.x, q.y, q.yaw, q.w, q.d) for q in draft.items
                                             if q.kind == "floormat"]):
            continue
        if how == "free":  # armchair: face the room centre
            yaw = math.atan2(-(W / 2 - cx), (D / 2 - cy))
        it = Item(kind, [], *dims, x=float(cx), y=float(cy), yaw=float(yaw))
        if kind in ("table", "dining_table"):
            draft.chair_anchors.append((it, "around"))
        if how != "floor":
            draft.rects.append(fp)
        return it
    return None


def _place_props(draft: _Draft, fam: Family) -> None:
    """Small props and table lamps on the surfaces (the clutter of real rooms)."""
    for it in draft.items:
        if it.kind in SURFACES:
            it.objs += _props_on(it, fam, draft.rng)


def _place_chairs(draft: _Draft, chair_dims: tuple) -> None:
    """The family's chair in front of each desk and around each table (some seats left empty), where it fits."""
    rng, W, D = draft.rng, draft.W, draft.D
    cw, cd, ch = chair_dims
    for anchor, mode in draft.chair_anchors:
        R = _rot(anchor.yaw)[:2, :2]
        if mode == "front1":
            spots = [(0.0, anchor.d / 2 + 0.15, math.pi)]
        else:
            spots = [(sx * anchor.w / 4, sy * (anchor.d / 2 + 0.2), (0 if sy < 0 else math.pi)) for sx in (-1, 1)
                     for sy in (-1, 1)] + [(sx * (anchor.w / 2 + 0.2), 0.0, sx * -math.pi / 2) for sx in (-1, 1)]
        anchor_fp = _footprint(anchor.x, anchor.y, anchor.yaw, anchor.w, anchor.d)
        for lx, ly, lyaw in spots:
            if mode == "around" and rng.uniform() < 0.3:
                continue
            p = np.array([anchor.x, anchor.y]) + R @ np.array([lx, ly])
            yaw = anchor.yaw + lyaw + rng.normal(0, 0.15)
            p += R @ np.array([rng.normal(0, 0.05), rng.normal(0, 0.05)])
            fp = _footprint(p[0], p[1], yaw, cw, cd)
            if fp[0] < 0.05 or fp[1] < 0.05 or fp[2] > W - 0.05 or fp[3] > D - 0.05:
                continue
            if _overlaps(fp, [r for r in draft.rects if not _overlaps(r, [anchor_fp], -0.01)], pad=0.02):
                continue
            draft.items.append(Item("chair", b_chair(chair_dims, {}), cw, cd, ch, float(p[0]), float(p[1]),
                                    float(yaw)))
            draft.rects.append(fp)


def _place_lights(draft: _Draft, fam: Family, seed: int, dim: bool) -> tuple[list, np.ndarray, np.ndarray]:
    """(lights, ambient, window emission): the family's ceiling fixtures (same positions and colour in every
    setting; their lamps are items), all on in a bright setting, one weak one in a dim setting (and dusk at the
    windows)."""
    W, D, H = draft.W, draft.D, draft.H
    lrng = np.random.default_rng([seed, 7919, fam.index, 2])
    n_lights = 1 if dim else fam.n_lights
    temp = fam.temp
    rgb = np.array([1.0, 0.85 + 0.12 * temp, 0.65 + 0.35 * temp])
    lights = []
    level = draft.rng.uniform(0.9, 1.1) * (0.25 if dim else 1.0)
    for k in range(fam.n_lights):
        pos = np.array([lrng.uniform(0.25, 0.75) * W, lrng.uniform(0.25, 0.75) * D, H - 0.25])
        power = lrng.uniform(4.0, 6.0) * (W * D / 20.0) ** 0.5 / fam.n_lights ** 0.5
        if k < n_lights:
            lights.append((pos, rgb * level * power))
        drop = fam.pendant  # a pendant hangs on a cord into the view; a flush fixture stays at the ceiling
        draft.items.append(Item("ceiling_lamp", [Obj(ID["lamp"], [(_cyl(0, 0, -0.2 - drop, 0.2, 0.14), "shade"),
                                                                (_cyl(0, 0, -0.06 - drop, 0.01, 0.06 + drop),
                                                                 "metal")])],
                                0.3, 0.3, 0.2, float(pos[0]), float(pos[1]), 0.0, H))
    ambient = rgb * (0.12 if not dim else 0.015)
    window_emission = np.array([0.9, 1.0, 1.2]) * (fam.window_level if not dim else 0.04)
    return lights, ambient, window_emission
