"""The procedural mini-Hypersim: furnished rooms, ray cast with embree, written in Hypersim's exact layout.

Words (design.md): a *setting* is one room configuration (folder ``ai_VVV_NNN``), a *scene* one camera trajectory
(``cam_XX``), a *frame* one image of it. A *family* is one volume ``ai_9FF``: its settings share the room type, the
furniture catalogue (object types and their dimensions), the materials, doors and windows, and differ in layout,
lighting and viewpoints -- the paper's "two neighbouring offices". Volumes start at 900 so a synthetic setting can
never be confused with a real Hypersim scene.

What makes it look like Hypersim where place recognition is decided (real Hypersim's statistics are in
`monolib/resources/fidelity_reference.csv`; `monolib.graphs.fidelity` measures them for every study,
`figures/fidelity.md`): each family has its own paints, woods,
tiles and fabrics drawn from a wide continuous space, so walls and floors of two places differ more than one wall
seen twice; surfaces carry clutter (vases, bottles, bowls, books, table lamps), floors carry plants, some families
have skirting boards and pendant lamps. The rooms have real Hypersim's depth and light: rooms of 5 to 10 m a
side (bathrooms 3-5 m), most with the next room behind an opening (an open-plan dining or kitchen area, often an L,
or a room behind a doorway: `rooms._make_annex`); large windows that show the outside 10 to 80 m
away (ground, facades, trees; a flat's street below: unlabelled geometry, the sky no depth); the
cameras walk as Hypersim's (`cameras.make_trajectories`: an artist's viewpoint across the room, then scored
random-walk steps); the light is daylight through the windows (the sky as an area light at each window, the sun's
patches), ceiling fixtures and lamps with inverse-square fall-off and shadows, corners darker and light bounced off
the walls' paint (`render.Renderer.shade`), exposed per setting as an artist would (`cameras.setting_exposure`).
The test split holds one setting per family (the `paper` protocol) and, for the first `test_siblings` families, a
sibling setting (the `siblings` protocol).

Every number that reaches a written file is computed with `monolib.data.exact` (products, norms, sin, exp, log in
float64 from correctly rounded elementwise operations) and rounded once to the stored dtype, so the files are the
same, bit for bit, whatever SIMD kernels numpy and OpenBLAS pick on the CPU; and with ``dataset.coplanar: exact``
(the default) the face each ray meets and whether a shadow ray is blocked are decided in float64
(`raycast.ExactHits`), Embree only naming the candidates, so that neither Embree's kernels nor the vendor's
approximate reciprocal decide a tie (`raycast`).
`tests/test_bitexact.py` checks these. The data stage does not use torch.

Everything is built in metres in a z-up world with the floor at z = 0; positions and camera centres are converted to
the setting's asset units (``meters_per_asset_unit`` = 0.01 or 0.0254) when written, as in Hypersim's
file layout (`monolib.data.hypersim` reads it; docs/data.md).

The modules, in the order they build on each other (each imports only those above it):

- `materials`: the materials of a family (`_family_materials`) and their procedural albedo (`_albedo`);
- `furniture`: mesh parts, objects and items, the furniture builders and their `CATALOGUE`;
- `rooms`: room types, families (`make_family`: the annex and the outside too) and the layout of one setting
  (`make_layout`: doors, windows, furniture, lights);
- `mesh`: the triangle mesh of a setting, its annex and the outside, with classes, instances and materials
  (`build_mesh`);
- `raycast`: the ray caster, Embree pinned to its AVX2 kernels so that every AMD CPU with AVX2 casts the same
  hits, and the float64 decision of ties for every x86 CPU (`RayCaster`, `ExactHits`);
- `render`: ray casting and shading (`Renderer`, `render_frame`);
- `cameras`: camera models, trajectories (`make_trajectories`, `view_score`) and exposures;
- `setting`: one setting built, rendered and written in Hypersim's layout (`render_setting`);
- `dataset`: the study's `plan`, setting keys, `render_dataset` (resumable, ``.tmp_*`` render folders, settings of
  another key set aside in ``.aside/``), the dataset-level metadata files and `benchmark`.

Public API: `render_dataset(study, out_dir)` and `benchmark()`; the names below are re-exported as well (the tests
use `plan`, `make_family`, `make_layout`, `render_setting`, `_setting_key`, ...).
"""
from __future__ import annotations

from monolib.data.synth.cameras import FOV_X, look_rotation, make_trajectories, scene_exposures, view_score
from monolib.data.synth.dataset import (CAMERA_COLUMNS, FORMAT_VERSION, SPLIT_COLUMNS, TRAJECTORY_COLUMNS, VOLUME0,
                                        _setting_key, benchmark, plan, render_dataset)
from monolib.data.synth.furniture import CATALOGUE, Item, Obj
from monolib.data.synth.materials import Material
from monolib.data.synth.mesh import SceneMesh, build_mesh
from monolib.data.synth.render import FrameOut, Renderer, render_frame
from monolib.data.synth.rooms import ROOM_TYPES, ROOMS, Family, Layout, make_family, make_layout
from monolib.data.synth.setting import build_setting, render_setting

__all__ = ["CAMERA_COLUMNS", "CATALOGUE", "FORMAT_VERSION", "FOV_X", "Family", "FrameOut", "Item", "Layout",
           "Material", "Obj", "ROOMS", "ROOM_TYPES", "Renderer", "SPLIT_COLUMNS", "SceneMesh", "TRAJECTORY_COLUMNS",
           "VOLUME0", "_setting_key", "benchmark", "build_mesh", "build_setting", "look_rotation", "make_family",
           "make_layout", "make_trajectories", "plan", "render_dataset", "render_frame",
           "render_setting", "scene_exposures", "view_score"]
