"""The furniture of the mini-Hypersim: mesh parts (boxes, cylinders), semantic objects (`Obj`), placed items
(`Item`), the builders of each piece of furniture and wall-mounted thing, and the `CATALOGUE` of their sizes and
placements."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from monolib.data import exact
from monolib.data.labels import ID


def _box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box (vertices (8,3), faces (12,3)) from corner lo to corner hi."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    v = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return v, f


def _bx(cx, cy, z0, sx, sy, sz):
    """Box centred at (cx, cy) in x/y, from height z0 up by sz."""
    return _box((cx - sx / 2, cy - sy / 2, z0), (cx + sx / 2, cy + sy / 2, z0 + sz))


def _cyl(cx, cy, z0, r, h, sections=14):
    a = np.linspace(0, 2 * np.pi, sections, endpoint=False)
    ring = np.stack([cx + r * exact.cos(a), cy + r * exact.sin(a)], 1)
    v = np.concatenate([np.c_[ring, np.full(sections, z0)], np.c_[ring, np.full(sections, z0 + h)],
                        [[cx, cy, z0], [cx, cy, z0 + h]]])
    f = []
    for i in range(sections):
        j = (i + 1) % sections
        f += [[i, j, sections + j], [i, sections + j, sections + i],
              [2 * sections, j, i], [2 * sections + 1, sections + i, sections + j]]
    return v, np.array(f)


@dataclass
class Obj:
    """One semantic instance: several mesh parts in the object's local frame (+y = front, z up)."""
    sem: int
    parts: list  # list of ((v, f), material key)


@dataclass
class Item:
    """A placed piece of furniture: objects, footprint (w, d) and pose (x, y, yaw, z0) in the room."""
    kind: str
    objs: list
    w: float
    d: float
    h: float
    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0
    z0: float = 0.0
    lights: list = field(default_factory=list)  # bulbs (x, y, z) in the item's frame: its lamps' point lights


# ---- furniture builders: local frame, footprint centred at the origin, front towards +y ----------------------

def _legs(w, d, h, t, inset=0.03):
    return [_bx(sx * (w / 2 - inset - t / 2), sy * (d / 2 - inset - t / 2), 0, t, t, h)
            for sx in (-1, 1) for sy in (-1, 1)]


def b_table(dim, mats, sem="table"):
    w, d, h = dim
    parts = [(_bx(0, 0, h - 0.04, w, d, 0.04), mats.get("top", "wood"))]
    parts += [(leg, mats.get("legs", "wood")) for leg in _legs(w, d, h - 0.04, 0.05)]
    return [Obj(ID[sem], parts)]


def b_desk(dim, mats):
    w, d, h = dim
    parts = [(_bx(0, 0, h - 0.035, w, d, 0.035), "wood"),
             (_bx(-w / 2 + 0.02, 0, 0, 0.03, d - 0.04, h - 0.035), "wood2"),
             (_bx(w / 2 - 0.22, 0, 0.05, 0.4, d - 0.06, h - 0.09), "wood2"),
             (_bx(0, -d / 2 + 0.03, 0.3, w - 0.1, 0.02, h - 0.34), "wood2")]
    return [Obj(ID["desk"], parts)]


def b_chair(dim, mats):
    w, d, h = dim
    seat = 0.45
    parts = [(_bx(0, 0, seat - 0.05, w, d, 0.05), "fabric"),
             (_bx(0, -d / 2 + 0.03, seat, w, 0.05, h - seat), "fabric")]
    parts += [(leg, "metal") for leg in _legs(w, d, seat - 0.05, 0.035, 0.02)]
    return [Obj(ID["chair"], parts)]


def b_sofa(dim, mats):
    w, d, h = dim
    arm = 0.18
    parts = [(_bx(0, 0.05, 0.08, w - 2 * arm, d - 0.2, 0.35), "fabric"),
             (_bx(0, -d / 2 + 0.1, 0.08, w, 0.2, h - 0.08), "fabric"),
             (_bx(-w / 2 + arm / 2, 0.05, 0.08, arm, d - 0.1, 0.55), "fabric"),
             (_bx(w / 2 - arm / 2, 0.05, 0.08, arm, d - 0.1, 0.55), "fabric"),
             (_bx(0, 0, 0, w - 0.1, d - 0.1, 0.08), "wood")]
    objs = [Obj(ID["sofa"], parts)]
    for sx in (-1, 1):
        objs.append(Obj(ID["pillow"], [(_bx(sx * (w / 2 - arm - 0.3), -d / 2 + 0.3, 0.43, 0.42, 0.14, 0.38),
                                        "pillow")]))
    return objs


def b_bed(dim, mats):
    w, d, h = dim
    parts = [(_bx(0, 0, 0, w, d, 0.3), "wood"), (_bx(0, 0.02, 0.3, w - 0.06, d - 0.1, 0.22), "fabric"),
             (_bx(0, -d / 2 + 0.04, 0, w, 0.08, h), "wood")]
    objs = [Obj(ID["bed"], parts)]
    n = 2 if w > 1.2 else 1
    for k in range(n):
        cx = (k - (n - 1) / 2) * (w / 2)
        objs.append(Obj(ID["pillow"], [(_bx(cx, -d / 2 + 0.3, 0.52, min(0.6, w / n - 0.1), 0.35, 0.14), "pillow")]))
    return objs


def b_boxlike(sem, mat, handles=True):
    def build(dim, mats):
        w, d, h = dim
        parts = [(_bx(0, 0, 0, w, d, h), mats.get("body", mat))]
        if handles:
            nd = max(1, int(h / 0.3))
            for k in range(nd):
                parts.append((_bx(0, d / 2 + 0.005, (k + 0.5) * h / nd - 0.01, min(0.2, w * 0.4), 0.012, 0.02),
                              "metal"))
        return [Obj(ID[sem], parts)]
    return build


def b_bookshelf(dim, mats, sem="bookshelf", books=True):
    w, d, h = dim
    t = 0.025
    frame = [(_bx(-w / 2 + t / 2, 0, 0, t, d, h), "wood"), (_bx(w / 2 - t / 2, 0, 0, t, d, h), "wood"),
             (_bx(0, -d / 2 + 0.005, 0, w, 0.01, h), "wood")]
    nshelf = max(2, int(h / 0.38))
    objs = []
    for k in range(nshelf + 1):
        z = k * (h - t) / nshelf
        frame.append((_bx(0, 0, z, w - 2 * t, d, t), "wood"))
        if books and k < nshelf:
            bh = min(0.3, (h - t) / nshelf - 0.06)
            bw = (w - 2 * t) * (0.5 + 0.45 * ((k * 7919) % 10) / 10)
            objs.append(Obj(ID["books"], [(_bx(-w / 2 + t + bw / 2, 0.01, z + t, bw, d * 0.8, bh), "books")]))
    return [Obj(ID[sem], frame)] + objs


def b_counter(dim, mats):
    w, d, h = dim
    objs = [Obj(ID["cabinet"], [(_bx(0, -0.02, 0.08, w, d - 0.04, h - 0.12), "wood2"),
                                (_bx(0, -0.05, 0, w - 0.04, d - 0.1, 0.08), "metal")]
                + [(_bx(-w / 2 + (k + 0.5) * w / max(1, int(w / 0.5)), d / 2 - 0.03, h - 0.2, 0.12, 0.015, 0.02),
                    "metal")
                   for k in range(max(1, int(w / 0.5)))]),
            Obj(ID["counter"], [(_bx(0, 0, h - 0.04, w + 0.02, d, 0.04), "stone")])]
    return objs


def b_kitchen_sink(dim, mats):
    objs = b_counter(dim, mats)
    w, d, h = dim
    objs.append(Obj(ID["sink"], [(_bx(0, 0.02, h, 0.55, 0.42, 0.015), "metal"),
                                 (_cyl(0, -d / 2 + 0.08, h, 0.02, 0.3), "metal")]))
    return objs


def b_vanity(dim, mats):
    w, d, h = dim
    return [Obj(ID["cabinet"], [(_bx(0, 0, 0, w, d, h - 0.03), "wood2")]),
            Obj(ID["sink"], [(_bx(0, 0, h - 0.03, w + 0.02, d + 0.02, 0.03), "white"),
                             (_bx(0, 0.04, h, w * 0.6, d * 0.55, 0.08), "white"),
                             (_cyl(0, -d / 2 + 0.06, h, 0.018, 0.22), "metal")])]


def b_toilet(dim, mats):
    w, d, h = dim
    return [Obj(ID["toilet"], [(_cyl(0, 0.06, 0, 0.16, 0.38), "white"),
                               (_bx(0, 0.08, 0.38, w * 0.9, d * 0.6, 0.04), "white"),
                               (_bx(0, -d / 2 + 0.1, 0.38, w, 0.2, 0.4), "white")])]


def b_bathtub(dim, mats):
    w, d, h = dim
    t = 0.07
    return [Obj(ID["bathtub"], [(_bx(0, 0, 0, w, d, h - 0.1), "white"),
                                (_bx(0, -d / 2 + t / 2, h - 0.1, w, t, 0.1), "white"),
                                (_bx(0, d / 2 - t / 2, h - 0.1, w, t, 0.1), "white"),
                                (_bx(-w / 2 + t / 2, 0, h - 0.1, t, d, 0.1), "white"),
                                (_bx(w / 2 - t / 2, 0, h - 0.1, t, d, 0.1), "white")])]


def b_fridge(dim, mats):
    w, d, h = dim
    return [Obj(ID["refrigerator"], [(_bx(0, 0, 0, w, d, h), "appliance"),
                                     (_bx(w / 2 - 0.06, d / 2 + 0.01, h * 0.45, 0.03, 0.03, h * 0.35), "metal")])]


def b_tvstand(dim, mats):
    w, d, h = dim
    tw = min(w * 0.9, 1.3)
    return [Obj(ID["otherfurniture"], [(_bx(0, 0, 0, w, d, h), "wood2")]),
            Obj(ID["television"], [(_bx(0, -0.02, h + 0.08, tw, 0.05, tw * 0.58), "screen"),
                                   (_bx(0, -0.02, h, 0.25, 0.15, 0.08), "metal")])]


def b_nightstand(dim, mats):
    w, d, h = dim
    return [Obj(ID["nightstand"], [(_bx(0, 0, 0, w, d, h), "wood"),
                                   (_bx(0, d / 2 + 0.005, h * 0.6, 0.12, 0.01, 0.02), "metal")]),
            Obj(ID["lamp"], [(_cyl(0, 0, h, 0.07, 0.03), "metal"), (_cyl(0, 0, h + 0.03, 0.015, 0.25), "metal"),
                             (_cyl(0, 0, h + 0.22, 0.15, 0.2), "shade")])]


def b_floorlamp(dim, mats):
    w, d, h = dim
    return [Obj(ID["lamp"], [(_cyl(0, 0, 0, 0.15, 0.03), "metal"), (_cyl(0, 0, 0.03, 0.015, h - 0.3), "metal"),
                             (_cyl(0, 0, h - 0.35, 0.2, 0.35), "shade")])]


def b_dresser(dim, mats):
    objs = b_boxlike("dresser", "wood")(dim, mats)
    w, d, h = dim
    objs.append(Obj(ID["otherprop"], [(_cyl(w / 4, 0, h, 0.06, 0.25), "prop0")]))
    return objs


def b_shelves(dim, mats):
    w, d, h = dim
    objs = [Obj(ID["shelves"], [(_bx(0, 0, z, w, d, 0.025), "wood") for z in np.linspace(0, h, 3)])]
    objs.append(Obj(ID["box"], [(_bx(-w / 4, 0, h / 2 + 0.025, 0.3, d * 0.8, min(0.25, h / 2 - 0.05)), "cardboard")]))
    objs.append(Obj(ID["otherprop"], [(_cyl(w / 4, 0, 0.025, 0.05, 0.18), "prop0")]))
    objs.append(Obj(ID["books"], [(_bx(w / 4, 0, h + 0.025, 0.3, d * 0.8, 0.22), "books")]))
    return objs


def b_boxes(dim, mats):
    w, d, h = dim
    return [Obj(ID["box"], [(_bx(0, 0, 0, w, d, h), "cardboard")]),
            Obj(ID["box"], [(_bx(0.03, -0.02, h, w * 0.7, d * 0.7, h * 0.6), "cardboard")])]


def b_floormat(dim, mats):
    w, d, h = dim
    return [Obj(ID["floormat"], [(_bx(0, 0, 0, w, d, 0.012), "mat")])]


def b_coffee_table(dim, mats):
    objs = b_table(dim, {})
    w, d, h = dim
    objs.append(Obj(ID["otherprop"], [(_cyl(w / 5, 0, h, 0.05, 0.22), "prop0")]))
    objs.append(Obj(ID["paper"], [(_bx(-w / 5, 0, h, 0.3, 0.22, 0.005), "paper")]))
    return objs


def b_plant(dim, mats):
    """A potted plant on the floor: pot and foliage are one small thing (NYU40 otherprop, as in Hypersim)."""
    w, d, h = dim
    return [Obj(ID["otherprop"], [(_cyl(0, 0, 0, w * 0.3, h * 0.3), "prop1"),
                                  (_cyl(0, 0, h * 0.3, w * 0.5, h * 0.7, 8), "leaves")])]


def b_side_table(dim, mats):
    return b_table(dim, {"top": "wood2", "legs": "wood2"})


def b_lounge_chair(dim, mats):
    w, d, h = dim
    parts = [(_bx(0, 0.03, 0.1, w - 0.1, d - 0.1, 0.32), "fabric2"),
             (_bx(0, -d / 2 + 0.08, 0.1, w, 0.16, h - 0.1), "fabric2"),
             (_bx(-w / 2 + 0.05, 0.03, 0.1, 0.1, d - 0.1, 0.52), "fabric2"),
             (_bx(w / 2 - 0.05, 0.03, 0.1, 0.1, d - 0.1, 0.52), "fabric2")]
    parts += [(leg, "wood") for leg in _legs(w, d, 0.1, 0.04, 0.04)]
    return [Obj(ID["chair"], parts)]


def b_work_desk(dim, mats):
    objs = b_desk(dim, mats)
    w, d, h = dim
    objs.append(Obj(ID["paper"], [(_bx(-w / 5, 0.05, h, 0.3, 0.22, 0.004), "paper")]))
    objs.append(Obj(ID["otherprop"], [(_bx(0, -d / 2 + 0.2, h, 0.5, 0.05, 0.32), "screen"),
                                      (_bx(0, -d / 2 + 0.2, h, 0.1, 0.1, 0.06), "metal")]))
    return objs


# ---- wall-mounted things (local frame: x along the wall, +y out of the wall, z up from the mount height) ---------

def w_picture(dim, mats, key="picture0"):
    w, d, h = dim
    return [Obj(ID["picture"], [(_bx(0, 0.015, 0, w + 0.06, 0.03, h + 0.06), "wood2"),
                                (_bx(0, 0.035, 0.03, w, 0.01, h), key)])]


def w_simple(sem, mat, thick=0.02):
    def build(dim, mats):
        w, d, h = dim
        return [Obj(ID[sem], [(_bx(0, thick / 2, 0, w, thick, h), mat)])]
    return build


def w_whiteboard(dim, mats):
    w, d, h = dim
    return [Obj(ID["whiteboard"], [(_bx(0, 0.015, 0, w, 0.03, h), "board"),
                                   (_bx(0, 0.05, -0.03, w, 0.06, 0.03), "metal")])]


def w_towel(dim, mats):
    w, d, h = dim
    return [Obj(ID["otherprop"], [(_cyl(-w / 2 - 0.05, 0.05, h, 0.012, 0.04), "metal")]),
            Obj(ID["towel"], [(_bx(0, 0.05, 0, w, 0.03, h), "towel")])]


# kind -> (builder, placement, dims (lo, hi) of width / depth / height in metres)
CATALOGUE = {
    "table": (b_table, "centre", ((1.0, 0.7, 0.72), (1.8, 1.0, 0.78))),
    "dining_table": (b_table, "centre", ((1.2, 0.8, 0.72), (2.0, 1.0, 0.78))),
    "coffee_table": (b_coffee_table, "centre", ((0.8, 0.5, 0.38), (1.2, 0.7, 0.48))),
    "desk": (b_work_desk, "wall", ((1.1, 0.6, 0.72), (1.6, 0.8, 0.76))),
    "student_desk": (b_desk, "grid", ((0.9, 0.5, 0.7), (1.2, 0.6, 0.74))),
    "chair": (b_chair, "near", ((0.42, 0.42, 0.85), (0.5, 0.5, 1.0))),
    "sofa": (b_sofa, "wall", ((1.6, 0.85, 0.8), (2.4, 1.0, 0.95))),
    "armchair": (b_sofa, "free", ((0.8, 0.8, 0.8), (1.0, 0.9, 0.95))),
    "bed": (b_bed, "wall", ((1.0, 1.95, 0.9), (1.8, 2.1, 1.2))),
    "nightstand": (b_nightstand, "wall", ((0.4, 0.35, 0.45), (0.55, 0.45, 0.6))),
    "dresser": (b_dresser, "wall", ((0.8, 0.45, 0.8), (1.4, 0.55, 1.1))),
    "cabinet": (b_boxlike("cabinet", "wood2"), "wall", ((0.6, 0.4, 0.8), (1.2, 0.5, 1.9))),
    "wardrobe": (b_boxlike("cabinet", "wood"), "wall", ((1.0, 0.55, 1.9), (1.6, 0.6, 2.2))),
    "bookshelf": (b_bookshelf, "wall", ((0.8, 0.3, 1.5), (1.2, 0.38, 2.1))),
    "shelves": (b_shelves, "wall_high", ((0.8, 0.25, 0.45), (1.2, 0.3, 0.6))),
    "counter": (b_counter, "wall", ((1.2, 0.6, 0.9), (2.4, 0.65, 0.92))),
    "kitchen_sink": (b_kitchen_sink, "wall", ((1.0, 0.6, 0.9), (1.4, 0.65, 0.92))),
    "fridge": (b_fridge, "wall", ((0.6, 0.65, 1.7), (0.8, 0.7, 1.95))),
    "upper_cabinet": (b_boxlike("cabinet", "wood2", False), "wall_high", ((1.0, 0.35, 0.6), (1.8, 0.38, 0.75))),
    "tvstand": (b_tvstand, "wall", ((1.2, 0.4, 0.45), (1.8, 0.5, 0.6))),
    "floorlamp": (b_floorlamp, "corner", ((0.4, 0.4, 1.5), (0.45, 0.45, 1.8))),
    "boxes": (b_boxes, "wall", ((0.35, 0.3, 0.25), (0.6, 0.45, 0.45))),
    "floormat": (b_floormat, "floor", ((1.2, 0.8, 0.0), (2.4, 1.7, 0.0))),
    "plant": (b_plant, "corner", ((0.35, 0.35, 0.6), (0.6, 0.6, 1.5))),
    "side_table": (b_side_table, "wall", ((0.4, 0.4, 0.5), (0.6, 0.55, 0.7))),
    "lounge_chair": (b_lounge_chair, "free", ((0.7, 0.7, 0.8), (0.85, 0.85, 0.95))),
    "toilet": (b_toilet, "wall", ((0.38, 0.65, 0.78), (0.42, 0.72, 0.82))),
    "bathtub": (b_bathtub, "wall", ((1.5, 0.7, 0.55), (1.8, 0.8, 0.6))),
    "vanity": (b_vanity, "wall", ((0.6, 0.45, 0.85), (1.2, 0.55, 0.9))),
    "otherfurniture": (b_boxlike("otherfurniture", "wood2"), "wall", ((0.5, 0.4, 0.5), (1.0, 0.5, 0.9))),
    # wall-mounted: placement "mount", dims w, depth, h; mount heights in MOUNT_Z
    "picture": (w_picture, "mount", ((0.4, 0.03, 0.3), (1.2, 0.03, 0.8))),
    "whiteboard": (w_whiteboard, "mount", ((1.6, 0.03, 0.9), (3.0, 0.03, 1.2))),
    "mirror": (w_simple("mirror", "mirror"), "mount", ((0.5, 0.02, 0.6), (0.9, 0.02, 1.0))),
    "towel": (w_towel, "mount", ((0.35, 0.03, 0.5), (0.55, 0.03, 0.7))),
    "wall_tv": (w_simple("television", "screen", 0.05), "mount", ((1.0, 0.05, 0.58), (1.4, 0.05, 0.8))),
}
MOUNT_Z = {"picture": (1.3, 1.6), "whiteboard": (0.9, 1.0), "mirror": (1.15, 1.3), "towel": (0.9, 1.1),
           "wall_tv": (1.0, 1.3)}
