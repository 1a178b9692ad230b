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
same on every CPU."""
from __future__ import annotations

import ctypes
import glob
import os
import sys
from typing import Optional

import numpy as np

ISA: Optional[str] = "avx2"  # Embree's kernels for every ray cast of the dataset (None: Embree's choice)
_PINNED = "pinned"
_warned = False


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
    return lib


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
    slot = ctypes.c_void_p.from_address(id(dev) + object.__basicsize__)
    old, slot.value = slot.value, new
    lib.rtcReleaseDevice(old)
    return dev


class RayCaster:
    """First hits and occlusion of rays against one triangle mesh (metres, float64 in, Embree's float32 inside)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, isa: Optional[str] = _PINNED, config: str = ""):
        from embreex.mesh_construction import TriangleMesh
        from embreex.rtcore_scene import EmbreeScene

        v = np.asarray(vertices, dtype=np.float64)
        self.origin = v.min(axis=0)
        self.device = device(ISA if isa == _PINNED else isa, config)  # kept: the scene holds its device's pointer
        self.scene = EmbreeScene(self.device)
        TriangleMesh(scene=self.scene, vertices=(v - self.origin).astype(np.float32),
                     indices=np.asarray(faces).astype(np.int32))

    def _origins(self, origins: np.ndarray) -> np.ndarray:
        return (np.asarray(origins, dtype=np.float64) - self.origin).astype(np.float32)

    def first(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Index of the first triangle each ray hits, or -1. The origins are rounded to float32 first; the
        directions to float32 and normalised again (float64 norm of the float32 squares)."""
        o = np.asarray(origins, dtype=np.float32)
        d = np.asarray(dirs, dtype=np.float32)
        sq = d * d
        norm = np.sqrt(sq[:, 0].astype(np.float64) + sq[:, 1] + sq[:, 2])
        unit = d * np.where(norm > 1e-12, 1.0 / norm, norm)[:, None]
        return self.scene.run(self._origins(o), unit.astype(np.float32))

    def occluded(self, origins: np.ndarray, dirs: np.ndarray, dists: np.ndarray) -> np.ndarray:
        """Whether something lies along each ray before `dists` (shadow rays; directions taken as they are)."""
        res = self.scene.run(self._origins(origins), np.asarray(dirs).astype(np.float32),
                             dists=np.asarray(dists).astype(np.float32), query="OCCLUDED")
        return res != -1
