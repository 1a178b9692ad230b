"""The dataset stage writes the same files, bit for bit, whatever SIMD the CPU has.

One small setting is rendered twice, each in its own interpreter: once as this machine runs, once with numpy's
dispatched SIMD kernels turned off (`NPY_DISABLE_CPU_FEATURES`: every dispatchable feature this CPU has beyond
numpy's baseline), OpenBLAS pinned to its AVX2 (Haswell) kernels (`OPENBLAS_CORETYPE`) and torch's kernels to their
default ones (`ATEN_CPU_CAPABILITY=default`). Every file written is compared byte for byte."""
import filecmp
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

RENDER = """
import json, sys
from pathlib import Path
from types import SimpleNamespace
from monolib.data import synth
ds = SimpleNamespace(width=128, height=96, train_settings=0, test_settings=1, test_siblings=0, family_size=1,
                     frames_per_setting=3, train_frames_per_setting=3, dim_fraction=0.0, tilt_shift_settings=0,
                     base_train_settings=None, coplanar="exact", workers=1)
synth.render_dataset(SimpleNamespace(seed=11, dataset=ds), Path(sys.argv[1]), progress=False)
from numpy._core._multiarray_umath import __cpu_features__ as have, __cpu_dispatch__ as dispatch
print(json.dumps([k for k in dispatch if have.get(k)]))
"""


def dispatched_features() -> list[str]:
    """numpy's dispatchable CPU features that this CPU has (beyond the baseline, which cannot be turned off)."""
    code = ("import json; from numpy._core._multiarray_umath import __cpu_features__ as h, __cpu_dispatch__ as d;"
            "print(json.dumps([k for k in d if h.get(k)]))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


def render(out: Path, env: dict) -> list[str]:
    """Render the small setting into `out` in a fresh interpreter with `env`; the numpy features it ran with."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), **env}
    res = subprocess.run([sys.executable, "-c", RENDER, str(out)], env=env, capture_output=True, text=True,
                         timeout=600)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


def test_dataset_is_bit_exact_without_the_cpus_simd_kernels(tmp_path):
    features = dispatched_features()
    if not features:
        pytest.skip("this CPU has no numpy SIMD features beyond the baseline: nothing to turn off")
    native = render(tmp_path / "native", {})
    reduced = render(tmp_path / "reduced", {"NPY_DISABLE_CPU_FEATURES": " ".join(features),
                                            "ATEN_CPU_CAPABILITY": "default",
                                            "OPENBLAS_CORETYPE": "Haswell"})
    assert native == features and reduced == [], (native, reduced)  # the second run really ran without them
    a, b = tmp_path / "native", tmp_path / "reduced"
    names = sorted(p.relative_to(a).as_posix() for p in a.rglob("*") if p.is_file())
    assert names == sorted(p.relative_to(b).as_posix() for p in b.rglob("*") if p.is_file())
    assert any(n.endswith(".color.hdf5") for n in names) and any(n.endswith(".tonemap.jpg") for n in names)
    differ = [n for n in names if not filecmp.cmp(a / n, b / n, shallow=False)]
    assert not differ, f"{len(differ)} of {len(names)} files differ, e.g. {differ[:8]}"


def test_exact_arithmetic_agrees_with_numpy_to_the_last_bits():
    """`monolib.data.exact` computes the same functions as numpy's kernels, to a few units in the last place."""
    import numpy as np

    from monolib.data import exact

    rng = np.random.default_rng(0)
    x = rng.uniform(-1e4, 1e4, 20000)
    assert np.abs(exact.sin(x) - np.sin(x)).max() < 1e-14 and np.abs(exact.cos(x) - np.cos(x)).max() < 1e-14
    y = rng.uniform(-40, 40, 20000)
    np.testing.assert_allclose(exact.exp(y), np.exp(y), rtol=1e-14)
    z = rng.uniform(1e-6, 100, 20000)
    np.testing.assert_allclose(exact.log(z), np.log(z), rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(exact.power(z, 1 / 2.2), z ** (1 / 2.2), rtol=1e-14)
    assert exact.power(np.array([0.0]), 2.2)[0] == 0.0 and exact.exp(np.array([-np.inf]))[0] == 0.0
    a, b = rng.normal(size=(7, 3)), rng.normal(size=(3, 4))
    np.testing.assert_allclose(exact.matmul(a, b), a @ b, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(exact.matmul(a, b[:, 0]), a @ b[:, 0], rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(exact.cross(a, a[::-1]), np.cross(a, a[::-1]), atol=1e-15)
    np.testing.assert_allclose(exact.norm(a), np.linalg.norm(a, axis=1), rtol=1e-15)
    T = np.eye(4)
    T[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    T[:3, 3] = rng.normal(size=3)
    np.testing.assert_allclose(exact.rigid_inverse(T), np.linalg.inv(T), atol=1e-14)


SETTING = """
import json, sys
from pathlib import Path
from monolib.data import digest
from monolib.data.synth import dataset, raycast
from monolib.params import load_study
isa = None if sys.argv[3] == "default" else sys.argv[3]
raycast.ISA = isa
study = load_study(Path("params/quick.yaml"))
s = next(s for s in dataset.plan(study) if s["name"] == sys.argv[1])
s.pop("coplanar", None)  # as `dataset.plan` writes it: only where it is not embree
if sys.argv[4] != "embree":
    s["coplanar"] = sys.argv[4]
key = dataset._setting_key(s, study)
dataset.render_setting(s, key, int(study.dataset.width), int(study.dataset.height), int(study.seed),
                       Path(sys.argv[2]) / s["name"])
print(json.dumps(digest.digest(sys.argv[2])["settings"][s["name"]]["kinds"]))
"""


def render_quick_setting(name: str, out: Path, isa: str, coplanar: str = "exact") -> dict:
    """One setting of the quick study rendered in a fresh interpreter with Embree's `isa` kernels ("default":
    Embree's choice for this CPU) and `coplanar` (`dataset.coplanar`): the sha256 of each kind of file it wrote."""
    res = subprocess.run([sys.executable, "-c", SETTING, name, str(out), isa, coplanar], cwd=ROOT, capture_output=True,
                         text=True, timeout=600, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


def test_a_quick_setting_renders_to_the_committed_digest_on_this_cpu(tmp_path):
    """The committed digest of quick's dataset was rendered on one CPU (docs/reproducibility.md names it): this CPU's
    render of one setting gives the same bytes, file kind by file kind (the setting's marker aside: it holds the code
    version), whatever its vendor and SIMD (quick's `coplanar: exact`; docs/reproducibility.md)."""
    from monolib.data.synth import raycast

    committed = json.loads((ROOT / "figures" / "dataset_digest.json").read_text())["settings"]
    name = "ai_916_001"  # a training setting of 20 frames
    fresh = render_quick_setting(name, tmp_path, raycast.ISA)
    marker = "monolib_synth_setting.json"
    want = {k: v for k, v in committed[name]["kinds"].items() if k != marker}
    got = {k: v for k, v in fresh.items() if k != marker}
    assert got == want, f"{name}: {sorted(k for k in set(want) | set(got) if want.get(k) != got.get(k))} differ"


def test_with_exact_coplanar_hits_embree_avx2_and_avx512_kernels_render_the_same_bytes(tmp_path):
    """`dataset.coplanar: exact`: a quick setting rendered with Embree's AVX2 kernels and with its AVX-512 ones gives
    the same files. Their approximate reciprocals differ (vrcpps and one Newton step against vrcp14ps), as Intel's
    and AMD's vrcpps do; with Embree deciding ties (`embree`), 0.8 % of this setting's pixels show another face."""
    from monolib.data.synth import raycast

    from numpy._core._multiarray_umath import __cpu_features__ as have

    if not (raycast.cpu_has_isa() and have.get("AVX512_SKX")):
        pytest.skip("this CPU runs no two of Embree's kernels that both have FMA (AVX2 and AVX-512)")
    name = "ai_916_001"
    avx2 = render_quick_setting(name, tmp_path / "avx2", "avx2", "exact")
    avx512 = render_quick_setting(name, tmp_path / "avx512", "default", "exact")
    assert avx2 == avx512, f"{name}: {sorted(k for k in avx2 if avx2[k] != avx512.get(k))} differ"


def test_exact_hits_decide_a_tie_the_same_whichever_face_embree_reports():
    """A floor and a rug in its plane (two owners that overlap): rays deep inside the overlap, on the rug's edge and on
    the floor alone are decided in float64 whatever face the first cast names (several namings), and a miss stays a
    miss."""
    import numpy as np

    from monolib.data.synth.raycast import ExactHits

    quad = lambda x0, y0, x1, y1, z: ([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]],  # noqa: E731
                                      [[0, 1, 2], [0, 2, 3]])
    v0, f0 = quad(0, 0, 4, 4, 0.0)  # the floor, owner 0
    v1, f1 = quad(1, 1, 2, 2, 0.0)  # a rug in the floor's plane, owner 1
    v = np.array(v0 + v1, float)
    f = np.array(f0 + [[a + 4, b + 4, c + 4] for a, b, c in f1])
    owner = np.array([0, 0, 1, 1])
    hits = ExactHits(v, f, owner)
    origins = np.array([[1.5, 1.5, 2.0], [3.0, 3.0, 2.0], [1.0, 1.5, 2.0]])  # rug, floor alone, the rug's edge
    dirs = np.tile([0.0, 0.0, -1.0], (3, 1))
    want = [2, 0, 2]  # the rug is the higher owner where both hold the point; the floor alone elsewhere
    for named in ([0, 0, 0], [2, 1, 3], [3, 0, 1]):
        got = hits.resolve(np.array(named), origins, dirs)[0]
        assert [int(owner[g]) for g in got] == [int(owner[w]) for w in want], (named, got)
    assert hits.resolve(np.array([-1, -1, -1]), origins, dirs)[0].tolist() == [-1, -1, -1]


def test_exact_hits_decide_the_same_when_embree_rounds_the_rays_otherwise():
    """Another CPU's Embree rounds otherwise; here every ray's float32 direction moved by one ulp before Embree sees
    it does it (primary rays, the shadow rays of every light, window and the sun, and the rays cast again). On frames
    of a quick setting (every third of each scene) Embree's own first hits then differ in hundreds of pixels; the
    frames rendered with `ExactHits` (colour, depth, positions, labels) do not differ in one value. Runs on every
    CPU."""
    import copy

    import numpy as np

    from monolib.data import exact
    from monolib.data.hypersim import Camera
    from monolib.data.synth import dataset
    from monolib.data.synth.cameras import _camera_M
    from monolib.data.synth.raycast import RayCaster
    from monolib.data.synth.render import render_frame
    from monolib.data.synth.setting import build_setting
    from monolib.params import load_study

    class Nudged(RayCaster):
        def _embree_first(self, origins, dirs, dists=None, output=False):
            d = np.nextafter(np.asarray(dirs, np.float32), np.float32(np.inf))
            return super()._embree_first(origins, d, dists, output)

    study = load_study(ROOT / "params" / "quick.yaml")
    s = {**next(s for s in dataset.plan(study) if s["name"] == "ai_934_001"), "coplanar": "exact"}
    _, _, _, scenes, r = build_setting(s, study.seed)
    nudged = copy.copy(r)
    nudged.caster = copy.copy(r.caster)
    nudged.caster.__class__ = Nudged
    rays = Camera(tuple(map(tuple, _camera_M(s, 256, 192))), float(s["meters_per_asset_unit"])).rays(192, 256)
    embree_differ, frames, values_differ = 0, 0, 0
    for eyes, Rs, _ in scenes:
        for eye, R in list(zip(eyes, Rs))[::3]:
            d = exact.normalize(exact.matmul(rays.reshape(-1, 3), R.T))
            o = np.broadcast_to(eye, d.shape)
            embree_differ += int((r.caster._embree_first(o, d) != nudged.caster._embree_first(o, d)).sum())
            a, b = render_frame(r, rays, eye, R, 1.0), render_frame(nudged, rays, eye, R, 1.0)
            for field in ("color", "depth", "position", "semantic", "instance", "entity"):
                x, y = getattr(a, field), getattr(b, field)
                same = (x == y) | (np.isnan(x) & np.isnan(y)) if x.dtype.kind == "f" else x == y
                values_differ += int((~same).sum())
            frames += 1
    assert frames >= 6 and embree_differ > 100 and values_differ == 0, (frames, embree_differ, values_differ)


def test_the_ray_caster_runs_embree_on_the_pinned_kernels_and_threads_do_not_change_its_hits():
    """Embree's own report (verbose=1) of the ISA of the caster's device; and the same rays hit the same triangles
    on one thread and on every core."""
    import numpy as np

    from monolib.data.synth import raycast

    if not raycast.cpu_has_isa():
        pytest.skip("this CPU has no AVX2")
    code = "from monolib.data.synth import raycast; raycast.device(raycast.ISA, 'verbose=1')"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    config = res.stdout.split("Config", 1)[1].split("Targets", 1)[0]
    assert " AVX2 " in config and "AVX512" not in config, config
    rng = np.random.default_rng(0)
    v = rng.uniform(-1, 1, (3000, 3))
    f = rng.integers(0, 3000, (1000, 3))
    o = rng.uniform(-0.1, 0.1, (20000, 3))
    d = rng.normal(size=(20000, 3))
    one, every = raycast.RayCaster(v, f, config="threads=1"), raycast.RayCaster(v, f)
    hits = one.first(o, d)
    assert (hits >= 0).mean() > 0.5 and np.array_equal(hits, every.first(o, d))
    dist = rng.uniform(0.1, 2, 20000)
    assert np.array_equal(one.occluded(o, d, dist), every.occluded(o, d, dist))
