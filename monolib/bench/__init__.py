"""Benchmarks that print figures (never asserted in tests): `monolib bench NAME`, a module each.

- `frames` (`make bench`): one frame's stages, graph construction against the original code's, kNN, perception fps;
- `render COMMIT` (`make bench-render`): the dataset stage of another commit's generator and of this one;
- `localizers` (`make bench-localizers`): each method's localizer: database bytes, ms per query, recall@1;
- `localize` (`make bench-localize`, module `photos`): recall@1 through the photo path, one image's latency;
- `imagenet` (`make bench-imagenet`): imagenet_vlad with and without PCA whitening;
- `allocator` (`make bench-allocator`): an image cell with glibc's malloc as it is and with ours;
- `cell` (`make bench-cell`): where a grid cell's seconds go (its stages, its training step's parts, operators);
- `selection` (`make bench-selection`, `monolib.retrieval.model_selection`): training rules on the training split;
- `grid` (`make bench-grid`, `monolib.study.scaling`): the grid on the local path and on Dask clusters.
"""
