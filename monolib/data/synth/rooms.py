"""Rooms of the mini-Hypersim: the room types, a *family* (`make_family`: room size, the furniture catalogue, the
materials and lights that its settings share) and the *layout* of one setting (`make_layout`: doors and windows,
the furniture placed against walls, on walls and on the floor, small props, chairs and lights)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from monolib.data import exact
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
    "kitchen": [("counter", 1, 2, 1.0), ("kitchen_sink", 1, 1, 1.0), ("fridge", 1, 1, 1.0),
                ("upper_cabinet", 1, 2, 0.8), ("table", 1, 1, 0.7), ("chair", 0, 0, 1.0), ("picture", 1, 1, 0.4),
                ("boxes", 1, 1, 0.3), ("shelves", 1, 1, 0.4), ("cabinet", 1, 1, 0.5), ("floormat", 1, 1, 0.3),
                ("plant", 1, 1, 0.4)],
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
SURFACES = {"table": (2, 0.1), "dining_table": (3, 0.0), "coffee_table": (2, 0.0), "desk": (2, 0.4),
            "student_desk": (1, 0.0), "nightstand": (1, 0.0), "dresser": (3, 0.3), "counter": (3, 0.1),
            "cabinet": (2, 0.2), "otherfurniture": (2, 0.3), "side_table": (1, 0.8), "shelves": (2, 0.0),
            "vanity": (1, 0.0), "bookshelf": (1, 0.0)}
# where the bulb of a lamp-carrying piece is (item frame): below its shade, beside the stem
LAMP_BULB = {"floorlamp": lambda dims: (0.06, 0.0, dims[2] - 0.40),
             "nightstand": lambda dims: (0.06, 0.0, dims[2] + 0.18)}
WALL_T = 0.12  # wall thickness (m): walls stand outside the room's floor plan

# room type -> ((W min, D min), (W max, D max)) in metres: rooms of real size (4 to 10 m a side; bathrooms smaller)
ROOM_SIZE = {"bathroom": ((3.0, 2.6), (5.0, 4.0)), "kitchen": ((4.5, 4.0), (8.0, 6.5)),
             "classroom": ((7.5, 6.5), (10.5, 10.0)), "library": ((6.0, 5.0), (10.5, 9.0))}
DEFAULT_ROOM_SIZE = ((5.0, 4.5), (10.0, 8.5))
# the next room, seen through the opening of one wall: room type -> (partner room types, open plan)
ANNEX = {"living room": (["dining room", "kitchen"], True), "dining room": (["kitchen", "living room"], True),
         "kitchen": (["dining room"], True), "bedroom": (["bathroom", "office"], False),
         "office": (["office", "library"], False), "classroom": (["classroom", "library"], False),
         "library": (["library", "office"], False), "bathroom": (["bedroom"], False)}
# kinds of which a larger room holds more (the counts of ROOMS are for a room of about 20 m2)
SINGLE = {"bed", "sofa", "tvstand", "fridge", "kitchen_sink", "toilet", "bathtub", "vanity", "whiteboard",
          "coffee_table", "dining_table", "mirror", "wardrobe", "dresser"}


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
    window_level: float = 2.0  # the sky's radiance on a bright day (dim settings: dusk)
    skirting: bool = False  # skirting boards along the walls (NYU40 otherstructure)
    pendant: float = 0.0  # how far the ceiling lamps hang below the ceiling (m; 0: flush)
    clutter: float = 0.6  # how many small props stand on the family's surfaces (0..1)
    recessed: bool = False  # downlights set into the ceiling: light without a lamp to see
    annex: Optional[dict] = None  # the next room behind one wall (`_make_annex`), shared by the family's settings
    outside: list = field(default_factory=list)  # ("ground", z), then ("building", x, y, w, d, top, k),
                                                 # ("tree", x, y, r, h)


def _scaled_count(kind: str, n: int, area: float) -> int:
    """How many of `kind` a room of `area` m2 holds, for `n` in a room of 20 m2 (single pieces stay single)."""
    if kind in SINGLE or n == 0:
        return n
    return int(round(n * min(2.5, max(1.0, area / 20.0)) ** 0.35))


def _draw_items(rng: np.random.Generator, room: str, area: float, keep: float = 1.0) -> list:
    """The catalogue of a room of type `room`: (kind, dims, extra) per piece (`keep`: probability scale)."""
    items = []
    pic = 0
    for kind, nmin, nmax, p in ROOMS[room]:
        if kind == "chair" or rng.uniform() > p * keep:
            continue
        n = _scaled_count(kind, int(rng.integers(nmin, nmax + 1)), area)
        lo_d, hi_d = CATALOGUE[kind][2]
        dims = tuple(float(rng.uniform(a, b)) for a, b in zip(lo_d, hi_d))
        for _ in range(n):
            extra = {}
            if kind == "picture":
                extra["mat"] = f"picture{pic % 3}"
                pic += 1
                dims = tuple(float(rng.uniform(a, b)) for a, b in zip(lo_d, hi_d))
            items.append((kind, dims, extra))
    return items


def _make_annex(rng: np.random.Generator, room: str, W: float, D: float, H: float) -> Optional[dict]:
    """The next room, behind one wall of the main room, through an opening in it: an open-plan area (living,
    dining and kitchen areas in one space; a wide opening, the two rooms often an L) or a room behind a doorway.
    Its floor plan is in the wall's frame: along the wall from `a0` to `a1` (it may reach past the main room's
    corner), `depth` beyond it; the opening spans `s0`-`s1` of the wall, up to `z1` (open plan: 0.3 m below the
    ceiling of height `H`)."""
    partners, open_plan = ANNEX[room]
    if rng.uniform() > (0.5 if room == "bathroom" else 0.9):
        return None
    w = int(rng.integers(4))
    L = W if w in (0, 2) else D
    other = partners[int(rng.integers(len(partners)))]
    if open_plan:
        width = float(rng.uniform(1.8, max(1.9, min(4.5, L - 0.8))))
        z1 = H - 0.3
    else:
        width, z1 = float(rng.uniform(0.9, 1.3)), 2.1
    s0 = float(rng.uniform(0.35, L - width - 0.35))
    s1 = s0 + width
    length = float(rng.uniform(max(width + 1.2, 4.0), max(width + 1.3, min(10.0, L + 3.0))))
    a0 = float(rng.uniform(s1 - length + 0.3, s0 - 0.3))
    lo, hi = ROOM_SIZE.get(other, DEFAULT_ROOM_SIZE)
    depth = float(rng.uniform(max(3.5, lo[1]), max(3.7, min(10.0, hi[1]))))
    return {"wall": w, "s0": s0, "s1": s1, "z1": z1, "a0": a0, "a1": a0 + length, "depth": depth, "room": other,
            "open_plan": open_plan, "window": bool(rng.uniform() < 0.7)}


def annex_frame(annex: dict, W: float, D: float) -> tuple[float, np.ndarray]:
    """(yaw, origin) of the annex's own frame in the world: annex point (u, v) = origin + R(yaw) (u, v); its wall
    0 (v = 0) is the main room's wall `annex["wall"]` seen from behind (u = a1 - s along it)."""
    o, t, nrm, _L = _wall_frame(annex["wall"], W, D)
    yaw = math.atan2(-t[1], -t[0])
    return yaw, o + t * annex["a1"] - nrm * WALL_T


def annex_box(annex: dict, W: float, D: float, pad: float = 0.0) -> tuple[float, float, float, float]:
    """(xmin, ymin, xmax, ymax) in the world of the annex's floor plan, its own walls `pad` thick (its wall 0 is
    the main room's)."""
    yaw, origin = annex_frame(annex, W, D)
    R = _rot(yaw)[:2, :2]
    L, Da = annex["a1"] - annex["a0"], annex["depth"]
    corners = np.array([origin + exact.matmul(R, np.array(c))
                        for c in ((-pad, 0), (L + pad, 0), (-pad, Da + pad), (L + pad, Da + pad))])
    return (float(corners[:, 0].min()), float(corners[:, 1].min()), float(corners[:, 0].max()),
            float(corners[:, 1].max()))


def house_box(fam: "Family") -> tuple[float, float, float, float]:
    """(xmin, ymin, xmax, ymax) of the main room and its annex, walls included."""
    W, D, _H = fam.size
    box = (-WALL_T, -WALL_T, W + WALL_T, D + WALL_T)
    if fam.annex is None:
        return box
    a = annex_box(fam.annex, W, D, WALL_T)
    return min(box[0], a[0]), min(box[1], a[1]), max(box[2], a[2]), max(box[3], a[3])


def _make_outside(rng: np.random.Generator, box: tuple, ground: float) -> list:
    """What the windows show, 10 to 80 m away: facades of buildings on most sides of the house, trees nearer, the
    ground at height `ground` (just below the floor, or the street below a flat)."""
    x0, y0, x1, y1 = box
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    out = [("ground", ground)]
    for side in range(4):
        for _ in range(int(rng.integers(2, 5))):
            dist, w, d, h = rng.uniform(15, 80), rng.uniform(10, 40), rng.uniform(8, 20), rng.uniform(8, 35)
            lateral = rng.uniform(-25, 25)
            if side == 0:
                x, y = cx + lateral, y0 - dist - d / 2
            elif side == 1:
                x, y = x1 + dist + w / 2, cy + lateral
            elif side == 2:
                x, y = cx + lateral, y1 + dist + d / 2
            else:
                x, y = x0 - dist - w / 2, cy + lateral
            if side in (1, 3):
                w, d = d, w
            out.append(("building", float(x), float(y), float(w), float(d), float(h + ground), int(rng.integers(3))))
    for _ in range(int(rng.integers(3, 11))):
        side, dist, lateral = int(rng.integers(4)), rng.uniform(8, 40), rng.uniform(-15, 15)
        x, y = [(cx + lateral, y0 - dist), (x1 + dist, cy + lateral), (cx + lateral, y1 + dist),
                (x0 - dist, cy + lateral)][side]
        out.append(("tree", float(x), float(y), float(rng.uniform(1.2, 3.0)), float(rng.uniform(4, 10))))
    return out


def make_family(seed: int, index: int, room: str) -> Family:
    rng = np.random.default_rng([seed, 7919, index])
    lo, hi = ROOM_SIZE.get(room, DEFAULT_ROOM_SIZE)
    W, D = rng.uniform(lo[0], hi[0]), rng.uniform(lo[1], hi[1])
    H = float(np.clip(rng.uniform(2.5, 3.0) + 0.06 * (max(W, D) - 5.0), 2.5, 3.6))
    mats = _family_materials(rng, room)
    temp = float(rng.uniform(0.2, 0.8))  # light colour temperature of the family's fixtures (0 warm .. 1 cool)
    items = _draw_items(rng, room, W * D, keep=0.6)
    chair_dims = tuple(float(rng.uniform(a, b)) for a, b in zip(*CATALOGUE["chair"][2]))
    items.append(("chair", chair_dims, {}))  # the family's chair model (the layout decides how many)
    wall_key = ["wall"] * 4
    if rng.uniform() < 0.5:
        wall_key[int(rng.integers(4))] = "wall2"
    n_lights = int(rng.integers(1, 3)) + (1 if W * D > 30 else 0) + (1 if W * D > 55 else 0)
    fam = Family(index, room, (W, D, H), mats, items, wall_key, temp, n_lights, float(rng.uniform(1.5, 2.5)),
                 skirting=bool(rng.uniform() < 0.35),
                 pendant=float(rng.uniform(0.3, 0.9)) if rng.uniform() < 0.35 else 0.0,
                 clutter=float(rng.uniform(0.2, 0.8)))
    fam.recessed = bool(rng.uniform() < 0.4)
    fam.annex = _make_annex(rng, room, W, D, H)
    if fam.annex is not None:
        a = fam.annex
        a["items"] = _draw_items(rng, a["room"], (a["a1"] - a["a0"]) * a["depth"], keep=0.45)
    fam.outside = _make_outside(rng, house_box(fam),
                                -float(rng.choice([0.4, rng.uniform(3.0, 9.0), rng.uniform(3.0, 9.0)])))
    return fam


# ---- the layout of one setting ---------------------------------------------------------------------------------

def _props_on(it: Item, fam: Family, rng: np.random.Generator) -> list:
    """Small things on the top of `it` (item-local frame): vases, bottles, bowls (otherprop), a stack of books, a
    sheet of paper, sometimes a table lamp. How many follows the family's clutter level."""
    n_max, p_lamp = SURFACES[it.kind]
    top = it.h
    objs = []
    if it.kind not in ("nightstand",) and rng.uniform() < p_lamp:  # nightstands already carry their lamp
        x, y = rng.uniform(-0.35, 0.35) * it.w, rng.uniform(-0.2, 0.2) * it.d
        objs.append(Obj(ID["lamp"], [(_cyl(x, y, top, 0.07, 0.03), "metal"),
                                     (_cyl(x, y, top + 0.03, 0.012, 0.22), "metal"),
                                     (_cyl(x, y, top + 0.2, 0.13, 0.18), "shade")]))
        it.lights.append((x + 0.05, y, top + 0.16))  # its bulb, just below the shade, beside the stem
    n = int(rng.binomial(n_max, fam.clutter))
    for _ in range(n):
        x, y = rng.uniform(-0.4, 0.4) * it.w, rng.uniform(-0.3, 0.3) * it.d
        kind = rng.choice(["vase", "bottle", "bowl", "books", "paper"], p=[0.4, 0.3, 0.2, 0.05, 0.05])
        mat = f"prop{int(rng.integers(N_PROP_MATERIALS))}"
        if kind == "vase":
            objs.append(Obj(ID["otherprop"],
                            [(_cyl(x, y, top, rng.uniform(0.05, 0.09), rng.uniform(0.15, 0.35), 10), mat)]))
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
    lights: list  # point lights: (position (3,), rgb (3,)), ceiling fixtures and lamps, all switched on
    ambient: np.ndarray  # light bounced around the rooms (rgb), before the corners' darkening
    sky: np.ndarray  # the sky's radiance (rgb) seen through the windows
    openings: list = field(default_factory=list)  # (wall, s0, s1, z0, z1, kind)
    sun: Optional[tuple] = None  # (unit direction towards the sun (3,), irradiance rgb (3,)), None: overcast / dusk
    windows: list = field(default_factory=list)  # (centre just outside (3,), inward normal (3,), area m2) per window
    rooms: list = field(default_factory=list)  # (xmin, ymin, xmax, ymax) floor plans: the room, then its annex
    annex: Optional[dict] = None  # the annex as built: the family's annex + "yaw", "origin", "openings"


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
    """One setting of a family, step by step: the family's doors, windows and opening to the next room, the
    furniture (classroom rows of desks, then the family's items from the largest footprint down: against a wall,
    mounted on a wall, or free on the floor), small props on the surfaces, chairs at the desks and tables, the same
    for the next room (`_place_annex`), and the lights. The steps draw from one generator of the setting in this
    order."""
    W, D, H = fam.size
    draft = _Draft(W, D, H, np.random.default_rng([seed, 104729, setting_index]))
    _place_openings(draft, fam, np.random.default_rng([seed, 7919, fam.index, 1]))  # shared by the family
    _furnish(draft, fam, fam.items)
    annex = _place_annex(draft, fam, np.random.default_rng([seed, 7919, fam.index, 3]))
    rooms = [(0.0, 0.0, W, D)]
    if annex is not None:
        rooms.append(annex["box"])
    lay = Layout(W, D, H, draft.items, draft.rects, [], np.zeros(3), np.zeros(3), draft.openings, rooms=rooms,
                 annex=annex)
    _place_lights(lay, draft, fam, seed, dim)
    return lay


def _furnish(draft: "_Draft", fam: Family, items: list) -> None:
    """The furniture of `items` (the family's chair model last), then props on the surfaces and the chairs."""
    furniture = [it for it in items if it[0] != "chair"]
    order = sorted(range(len(furniture)), key=lambda i: -furniture[i][1][0] * furniture[i][1][1])
    _place_desk_rows(draft, [furniture[i] for i in order if CATALOGUE[furniture[i][0]][1] == "grid"])
    for i in order:
        _place_furniture(draft, *furniture[i])
    _place_props(draft, fam)
    _place_chairs(draft, [it[1] for it in fam.items if it[0] == "chair"][0])


def _place_annex(draft: "_Draft", fam: Family, orng: np.random.Generator) -> Optional[dict]:
    """Furnish the family's annex in its own frame (its wall 0 holds the opening to the main room, kept free; its
    far wall a window when the family has one there) and move its items into the world. Returns the annex as built:
    the family's dict + "yaw", "origin", "openings" (annex frame), "box" (world floor plan)."""
    if fam.annex is None:
        return None
    a = fam.annex
    L, Da = a["a1"] - a["a0"], a["depth"]
    sub = _Draft(L, Da, draft.H, draft.rng)
    u0, u1 = a["a1"] - a["s1"], a["a1"] - a["s0"]
    sub.openings.append((0, u0, u1, 0.0, a["z1"], "opening"))
    sub.wall_used[0].append((u0, u1))
    sub.rects.append((u0 - 0.1, 0.0, u1 + 0.1, 1.0))  # the way through stays free
    if a["window"] and L > 2.0:
        width = float(orng.uniform(1.0, min(3.0, L - 0.8)))
        s0 = float(orng.uniform(0.3, L - width - 0.3))
        zlo = float(orng.uniform(0.4, 0.9))
        sub.openings.append((2, s0, s0 + width, zlo, min(draft.H - 0.2, zlo + float(orng.uniform(1.4, 2.2))), "window"))
        sub.wall_used[2].append((s0, s0 + width))
    _furnish(sub, fam, a["items"] + [it for it in fam.items if it[0] == "chair"])
    yaw, origin = annex_frame(a, draft.W, draft.D)
    R = _rot(yaw)[:2, :2]
    for it in sub.items:
        it.x, it.y = (float(v) for v in origin + exact.matmul(R, np.array([it.x, it.y])))
        it.yaw += yaw
        draft.items.append(it)
    return dict(a, yaw=yaw, origin=origin, openings=sub.openings, box=annex_box(a, draft.W, draft.D), W=L, D=Da)


def _place_openings(draft: _Draft, fam: Family, orng: np.random.Generator) -> None:
    """The opening to the next room (the family's annex), doors (their swing kept free on the floor) and windows
    (large ones in large rooms: they show the outside) on the walls, from the family's generator `orng`."""
    W, D, H = draft.W, draft.D, draft.H
    if fam.annex is not None:
        a = fam.annex
        w = a["wall"]
        draft.wall_used[w].append((a["s0"], a["s1"]))
        draft.openings.append((w, a["s0"], a["s1"], 0.0, a["z1"], "opening"))
        o, t, nrm, _L = _wall_frame(w, W, D)
        c = o + t * (a["s0"] + a["s1"]) / 2 + nrm * 0.5
        draft.rects.append(_footprint(c[0], c[1], w * math.pi / 2, a["s1"] - a["s0"] + 0.2, 1.0))
    n_doors = 1 + int(orng.uniform() < 0.25) - int(fam.annex is not None and orng.uniform() < 0.5)
    big = max(W, D)
    n_windows = int(orng.integers(0 if fam.room == "bathroom" else 2, 4 + (big > 6.0) + (big > 8.0)))
    for kind, n in (("door", n_doors), ("window", n_windows)):
        for _ in range(n):
            for _try in range(30):
                w = int(orng.integers(4))
                o, t, nrm, L = _wall_frame(w, W, D)
                ow = orng.uniform(0.8, 0.95) if kind == "door" else orng.uniform(1.5, max(1.55, min(5.0, L - 0.8)))
                s0 = orng.uniform(0.3, L - ow - 0.3) if L - ow - 0.6 > 0 else None
                if s0 is None or any(s0 < b + 0.2 and a < s0 + ow + 0.2 for a, b in draft.wall_used[w]):
                    continue
                draft.wall_used[w].append((s0, s0 + ow))
                if kind == "door":
                    z0, z1 = 0.0, 2.05
                    c = o + t * (s0 + ow / 2) + nrm * 0.5
                    draft.rects.append(_footprint(c[0], c[1], w * math.pi / 2, ow + 0.2, 1.0))  # keep the swing free
                else:
                    z0 = orng.uniform(0.1, 0.6)
                    z1 = min(H - 0.15, z0 + orng.uniform(1.9, 2.6))
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
        if kind in LAMP_BULB:
            it.lights.append(LAMP_BULB[kind](dims))
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
            p = np.array([anchor.x, anchor.y]) + exact.matmul(R, np.array([lx, ly]))
            yaw = anchor.yaw + lyaw + rng.normal(0, 0.15)
            p += exact.matmul(R, np.array([rng.normal(0, 0.05), rng.normal(0, 0.05)]))
            fp = _footprint(p[0], p[1], yaw, cw, cd)
            if fp[0] < 0.05 or fp[1] < 0.05 or fp[2] > W - 0.05 or fp[3] > D - 0.05:
                continue
            if _overlaps(fp, [r for r in draft.rects if not _overlaps(r, [anchor_fp], -0.01)], pad=0.02):
                continue
            draft.items.append(Item("chair", b_chair(chair_dims, {}), cw, cd, ch, float(p[0]), float(p[1]),
                                    float(yaw)))
            draft.rects.append(fp)


def _place_lights(lay: Layout, draft: _Draft, fam: Family, seed: int, dim: bool) -> None:
    """The light of one setting, into `lay`: daylight (the sky through every window, sampled at its centre, and on
    a sunny day the sun, whose patches fall through the windows; dusk in a dim setting), the family's ceiling
    fixtures (same positions and colour in every setting; their lamps are items unless the family's are recessed
    downlights; all on in a bright setting, one weak one in a dim setting), one fixture in the annex, the floor, table
    and bedside lamps (some switched on), and the light bounced off the walls (tinted by their paint)."""
    W, D, H = draft.W, draft.D, draft.H
    lrng = np.random.default_rng([seed, 7919, fam.index, 2])
    rng = draft.rng
    n_on = 1 if dim else fam.n_lights
    rgb = np.array([1.0, 0.85 + 0.12 * fam.temp, 0.65 + 0.35 * fam.temp])
    level = rng.uniform(0.9, 1.1) * (0.5 if dim else 1.0)
    flux = 0.0
    for k in range(fam.n_lights):
        pos = np.array([lrng.uniform(0.2, 0.8) * W, lrng.uniform(0.2, 0.8) * D, H - 0.25 - fam.pendant])
        power = lrng.uniform(3.0, 5.0)
        if k < n_on:
            bulb = pos + np.array([0.0, 0.0, -0.1]) if not fam.recessed else np.array([pos[0], pos[1], H - 0.05])
            lay.lights.append((bulb, rgb * level * power))
            flux += level * power
        if fam.recessed:
            continue
        drop = fam.pendant  # a pendant hangs on a cord into the view; a flush fixture stays at the ceiling
        draft.items.append(Item("ceiling_lamp", [Obj(ID["lamp"], [(_cyl(0, 0, -0.2 - drop, 0.2, 0.14), "shade"),
                                                                (_cyl(0, 0, -0.06 - drop, 0.01, 0.06 + drop),
                                                                 "metal")])],
                                0.3, 0.3, 0.2, float(pos[0]), float(pos[1]), 0.0, H))
    area = W * D
    if lay.annex is not None:
        a = lay.annex
        x0, y0, x1, y1 = a["box"]
        pos = np.array([(x0 + x1) / 2, (y0 + y1) / 2, H - (0.05 if fam.recessed else 0.35)])
        if not dim or rng.uniform() < 0.5:
            power = lrng.uniform(3.0, 5.0) * level
            lay.lights.append((pos, rgb * power))
            flux += power
        if not fam.recessed:
            draft.items.append(Item("ceiling_lamp", [Obj(ID["lamp"], [(_cyl(0, 0, -0.15, 0.18, 0.1), "shade")])],
                                    0.3, 0.3, 0.1, float(pos[0]), float(pos[1]), 0.0, H))
        area += (x1 - x0) * (y1 - y0)
    warm = np.array([1.0, 0.78, 0.5])
    for it in draft.items:  # lamps: on in most evenings, in some days
        for local in it.lights:
            if rng.uniform() < (0.85 if dim else 0.45):
                p = np.array([it.x, it.y, it.z0]) + exact.matmul(_rot(it.yaw), np.asarray(local))
                power = rng.uniform(0.6, 1.2) * (1.6 if it.kind == "floorlamp" else 1.0)
                lay.lights.append((p, warm * power))
                flux += power
    # daylight: the sky through the windows, and the sun on a sunny day
    # daylight outshines the lamps (as a sky of thousands of cd/m2 outshines bulbs of about a hundred cd)
    sky_level = 10.0 * fam.window_level * (0.05 if dim else rng.uniform(0.8, 1.25))  # dim: dusk
    lay.sky = np.array([0.75, 0.9, 1.2]) * sky_level
    if not dim and rng.uniform() < 0.65:
        az, el = rng.uniform(0, 2 * math.pi), rng.uniform(math.radians(15), math.radians(50))
        direction = np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])
        lay.sun = (direction, np.array([1.0, 0.92, 0.8]) * sky_level * rng.uniform(2.0, 4.0))
    window_area = 0.0
    for room, openings, yaw, origin in _rooms_openings(lay):
        R = _rot(yaw)
        for (w, s0, s1, z0, z1, kind) in openings:
            if kind != "window":
                continue
            o, t, nrm, _L = _wall_frame(w, room[0], room[1])
            c2 = o + t * (s0 + 0.3 * (s1 - s0)) - nrm * (WALL_T + 0.05)  # beside the mullion
            centre = np.r_[origin + exact.matmul(R[:2, :2], c2), (z0 + z1) / 2]
            normal = exact.matmul(R, np.r_[nrm, 0.0])
            lay.windows.append((centre, normal, (s1 - s0) * (z1 - z0)))
            window_area += (s1 - s0) * (z1 - z0)
    # bounced light: a share of what the lamps and windows bring in, spread over the floor area, tinted by the walls
    wall = np.asarray(fam.materials["wall"].base)
    tint = 0.6 + 0.4 * wall / max(float(wall.mean()), 1e-3)
    daylight = sky_level * window_area * (1.0 + (3.0 if lay.sun is not None else 0.0))
    lay.ambient = tint * (0.1 * flux + 0.03 * daylight) / max(area, 1.0) + (0.004 if dim else 0.0)


def _rooms_openings(lay: Layout) -> list:
    """((W, D), openings, yaw, origin) of the main room and of its annex."""
    out = [((lay.W, lay.D), lay.openings, 0.0, np.zeros(2))]
    if lay.annex is not None:
        a = lay.annex
        out.append(((a["W"], a["D"]), a["openings"], a["yaw"], np.asarray(a["origin"])))
    return out
