"""The materials of the mini-Hypersim: each family's paints, woods, tiles, fabrics, ... (`_family_materials`) and
their procedural albedo at a surface point (`_albedo`)."""
from __future__ import annotations

import colorsys
from dataclasses import dataclass

import numpy as np

from monolib.data import exact


N_PROP_MATERIALS = 4  # colours of a family's small props

PAINT, WOOD, FABRIC, TILES, PICTURE, BOOKS, PLAIN, STONE, RUG, FACADE = range(10)


@dataclass
class Material:
    kind: int
    base: tuple
    alt: tuple = (0.0, 0.0, 0.0)
    scale: float = 1.0
    seed: float = 0.0
    emission: tuple = (0.0, 0.0, 0.0)


def _hsv(h: float, s: float, v: float) -> tuple:
    return tuple(float(exact.power(c, 2.2)) for c in colorsys.hsv_to_rgb(h % 1.0, s, v))  # sRGB-ish -> linear albedo


def _family_materials(rng: np.random.Generator, room: str) -> dict[str, Material]:
    """One family's materials, drawn from a wide continuous space of paints, woods, tiles and fabrics.

    Every setting of the family (siblings included) uses exactly these; two families almost never share a wall or
    floor colour. Real Hypersim rooms differ this way: between two places the wall and floor colours spread 2.6
    times more than between two frames of one place (`monolib/resources/fidelity_reference.csv`).
    """
    u = rng.uniform

    def paint(sat_hi=0.8, v=(0.12, 0.95)) -> Material:
        # a third of the paints are near-neutral (white, grey, beige), the rest carry a colour
        sat = u(0.0, 0.08) if u() < 0.33 else u(0.1, sat_hi)
        return Material(PAINT, _hsv(u(0, 1), sat, u(*v)), seed=u(0, 100))

    def wood(v=(0.1, 0.9)) -> Material:
        val = u(*v)
        return Material(WOOD, _hsv(u(0.03, 0.11), u(0.3, 0.75), val), _hsv(u(0.03, 0.1), u(0.45, 0.85), val * 0.55),
                        u(40, 110), u(0, 100))

    def fabric(scale=(150, 320)) -> Material:
        return Material(FABRIC, _hsv(u(0, 1), u(0.05, 0.6), u(0.25, 0.85)), scale=u(*scale), seed=u(0, 100))

    def tiles() -> Material:
        h, v = u(0, 1), u(0.15, 0.95)
        return Material(TILES, _hsv(h, u(0.0, 0.4), v), _hsv(h, 0.05, v * 0.55), u(0.2, 0.5), u(0, 100))

    def rug() -> Material:
        h = u(0, 1)
        return Material(RUG, _hsv(h, u(0.15, 0.6), u(0.25, 0.75)), _hsv(h + u(-0.15, 0.15), u(0.1, 0.5), u(0.4, 0.85)),
                        u(200, 400), u(0, 100))

    def stone() -> Material:
        h, v = u(0.0, 1.0), u(0.35, 0.9)
        return Material(STONE, _hsv(h, u(0.02, 0.2), v), _hsv(h, 0.1, v * 0.7), u(60, 120), u(0, 100))

    m: dict[str, Material] = {}
    r = u()
    m["wall"] = paint() if r < 0.8 else (wood((0.35, 0.8)) if r < 0.9 else stone())
    m["wall2"] = paint()  # a feature wall (half of the families paint one wall differently)
    m["ceiling"] = Material(PAINT, _hsv(u(0.05, 0.15), u(0.0, 0.08), u(0.8, 0.95)), seed=3.0)
    if room in ("kitchen", "bathroom"):
        m["floor"] = tiles() if u() < 0.75 else stone()
    else:
        r = u()
        m["floor"] = wood() if r < 0.5 else (rug() if r < 0.75 else (tiles() if r < 0.9 else stone()))
    m["door"] = wood() if u() < 0.6 else paint(0.5, (0.2, 0.95))
    m["frame"] = Material(PAINT, _hsv(u(0, 1), u(0.0, 0.1), u(0.7, 0.95)), seed=2.0)
    m["skirting"] = m["frame"] if u() < 0.5 else wood()
    m["wood"] = wood()
    m["wood2"] = wood() if u() < 0.5 else paint(0.6, (0.2, 0.95))
    m["fabric"] = fabric()
    m["fabric2"] = fabric()
    m["pillow"] = fabric()
    m["metal"] = Material(PLAIN, _hsv(0.6, 0.03, u(0.2, 0.75)))
    m["white"] = Material(PLAIN, _hsv(0.6, 0.02, 0.92))
    m["appliance"] = paint(0.5, (0.3, 0.9)) if u() < 0.3 else Material(PLAIN, _hsv(0.6, 0.02, u(0.75, 0.9)))
    m["screen"] = Material(PLAIN, (0.01, 0.01, 0.012))
    m["books"] = Material(BOOKS, (0.5, 0.3, 0.2), scale=u(0.025, 0.045), seed=u(0, 100))
    m["stone"] = stone()
    m["board"] = Material(PLAIN, (0.92, 0.93, 0.93))
    m["mat"] = rug()
    m["cardboard"] = Material(PLAIN, _hsv(0.085, 0.5, 0.65))
    m["shade"] = Material(FABRIC, _hsv(u(0.05, 0.15), u(0.05, 0.3), 0.9), scale=300, seed=u(0, 100),
                          emission=(0.6, 0.5, 0.35))
    m["towel"] = fabric()
    m["curtain"] = fabric((15, 30))
    for k in range(N_PROP_MATERIALS):  # vases, bottles, bowls, plant pots: the family's own small things
        m[f"prop{k}"] = Material(PAINT, _hsv(u(0, 1), u(0.1, 0.8), u(0.2, 0.95)), seed=u(0, 100))
    m["leaves"] = Material(FABRIC, _hsv(u(0.22, 0.4), u(0.4, 0.8), u(0.25, 0.6)), scale=u(60, 120), seed=u(0, 100))
    m["paper"] = Material(PLAIN, (0.85, 0.85, 0.82))
    m["mirror"] = Material(PLAIN, (0.55, 0.6, 0.62), emission=(0.05, 0.05, 0.06))
    for k in range(3):  # the outside: facades with rows of dark windows, the ground, tree bark
        m[f"facade{k}"] = Material(FACADE, _hsv(u(0, 1), u(0.0, 0.35), u(0.35, 0.9)), (0.03, 0.035, 0.045), u(2.5, 4.0),
                                   u(0, 100))
    m["ground"] = Material(STONE, _hsv(u(0.15, 0.35), u(0.15, 0.5), u(0.25, 0.5)), scale=u(5, 15), seed=u(0, 100))
    m["bark"] = Material(PLAIN, _hsv(0.07, 0.5, 0.3))
    for k in range(3):
        m[f"picture{k}"] = Material(PICTURE, _hsv(u(0, 1), u(0.3, 0.8), u(0.3, 0.9)),
                                    _hsv(u(0, 1), u(0.3, 0.8), u(0.3, 0.9)), u(2, 7), u(0, 100))
    return m


def _hash(*xs: np.ndarray, seed: float = 0.0) -> np.ndarray:
    """A cheap deterministic hash of integer lattice coordinates -> [0, 1)."""
    s = seed * 0.731 + 0.1
    for i, x in enumerate(xs):
        s = s + np.asarray(x, np.float64) * (12.9898 + 31.4159 * i)
    return np.mod(exact.sin(s) * 43758.5453, 1.0)


def _wave_noise(p: np.ndarray, seed: float, freq: float) -> np.ndarray:
    """Smooth noise in [-1, 1] from three seeded plane waves (vectorised)."""
    out = np.zeros(len(p))
    r = np.random.default_rng(int(seed * 1000) % (2 ** 31))
    for k in range(3):
        d = r.normal(size=3)
        d = exact.normalize(d)
        out += exact.sin(exact.matmul(p, d) * freq * (1.0 + 0.7 * k) + r.uniform(0, 6.28))
    return out / 3.0


def _albedo(mat: Material, p: np.ndarray) -> np.ndarray:
    """(n, 3) albedo of material `mat` at local points p (n, 3) in metres."""
    base = np.asarray(mat.base)
    alt = np.asarray(mat.alt)
    n = len(p)
    if mat.kind == PAINT:
        return base * (1.0 + 0.04 * _wave_noise(p, mat.seed, 3.0))[:, None]
    if mat.kind == WOOD:
        t = (p[:, 1] * 0.7 + p[:, 2]) * mat.scale + 2.5 * _wave_noise(p, mat.seed, 2.0) + 4 * exact.sin(p[:, 0] * 1.3)
        g = 0.5 + 0.5 * exact.sin(t)
        g = g * g * g
        plank = _hash(np.floor(p[:, 1] / 0.18), seed=mat.seed)[:, None] * 0.2 + 0.9
        g = 0.6 * g[:, None]
        return (base * (1 - g) + alt * g) * plank
    if mat.kind == FABRIC:
        w = exact.sin(p[:, 0] * mat.scale) * exact.sin((p[:, 1] + p[:, 2]) * mat.scale)
        return base * (0.9 + 0.06 * w + 0.06 * _wave_noise(p, mat.seed, 6.0))[:, None]
    if mat.kind == TILES:
        s = mat.scale
        fx, fy = np.mod(p[:, 0] / s, 1.0), np.mod(p[:, 1] / s, 1.0)
        grout = (np.minimum(fx, fy) < 0.035)[:, None]
        var = 0.92 + 0.16 * _hash(np.floor(p[:, 0] / s), np.floor(p[:, 1] / s), seed=mat.seed)[:, None]
        return np.where(grout, alt, base * var)
    if mat.kind == PICTURE:
        cu, cv = np.floor(p[:, 0] * mat.scale), np.floor(p[:, 2] * mat.scale * 0.8)
        h = _hash(cu, cv, seed=mat.seed)[:, None]
        h2 = _hash(cu + 7, cv - 3, seed=mat.seed)[:, None]
        wave = (0.5 + 0.5 * exact.sin(p[:, 0] * 9 + p[:, 2] * 5 + mat.seed))[:, None]
        col = base * h + alt * (1 - h)
        return np.clip(col * (0.5 + 0.6 * wave) + 0.25 * h2 * (1 - base), 0.0, 1.0)
    if mat.kind == BOOKS:
        k = np.floor(p[:, 0] / mat.scale)
        h = np.stack([_hash(k, seed=mat.seed + j) for j in range(3)], 1)
        return 0.05 + 0.55 * h * np.sqrt(h)
    if mat.kind == STONE:
        speck = _hash(np.floor(p[:, 0] * mat.scale), np.floor(p[:, 1] * mat.scale), np.floor(p[:, 2] * mat.scale),
                      seed=mat.seed)[:, None]
        return base * (0.85 + 0.3 * speck)
    if mat.kind == RUG:
        border = np.minimum(np.abs(np.mod(p[:, 0] * 2.0, 1.0) - 0.5), np.abs(np.mod(p[:, 1] * 2.0, 1.0) - 0.5))
        stripe = (border > 0.42)[:, None]
        w = exact.sin(p[:, 0] * mat.scale) * exact.sin(p[:, 1] * mat.scale)
        return np.where(stripe, alt, base) * (0.9 + 0.08 * w)[:, None]
    if mat.kind == FACADE:  # storeys and bays of mat.scale metres, a dark window in each
        fu = np.mod((p[:, 0] + p[:, 1]) / mat.scale, 1.0)
        fz = np.mod(p[:, 2] / mat.scale, 1.0)
        pane = ((fu > 0.25) & (fu < 0.75) & (fz > 0.3) & (fz < 0.8))[:, None]
        return np.where(pane, alt, base * (0.9 + 0.1 * _hash(np.floor(p[:, 2] / mat.scale), seed=mat.seed))[:, None])
    return np.broadcast_to(base, (n, 3)).astype(np.float64)
