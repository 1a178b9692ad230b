# Two commands do all the set-up on a fresh machine:
#   make study   creates .venv/, installs the project, runs the default (quick) study and writes figures/
#   make test    creates .venv/, installs the project, runs the whole test suite (pytest + nbval)
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
STUDY ?= quick
NEED_GB ?= 7
TEST_WORKERS ?= 2
export MPLBACKEND := agg
export PYTHONHASHSEED := 0

.PHONY: install lock readme study-file-doc study paper-scale training-size ablations direction colour real test-fast verify perception-long scratch smoke zoo zoo-pilot test bench bench-grid bench-render bench-localizers bench-localize bench-allocator bench-cell bench-imagenet bench-selection bench-selection-real data-edits clean-runs

install: $(STAMP)

# From requirements.lock (the exact versions and files the committed figures were made with: make lock) when it
# is for this Python and platform, else from pyproject.toml's ranges (said on stderr).
# The environment takes about 6.5 GB (torch 2.14.1 is a CUDA build): say so up front rather than fail half-way
# through pip with "No space left on device".
$(STAMP): pyproject.toml requirements.lock
	@test -x $(PY) || $(PYTHON) -c "import shutil, sys; free = shutil.disk_usage('.').free / 1e9; \
	sys.exit(0 if free >= $(NEED_GB) else f'make install: {free:.1f} GB free on the disk of $(CURDIR), \
	the virtual environment $(VENV)/ needs about $(NEED_GB) GB (torch 2.14.1 with its CUDA libraries). Free some space and run make again.')"
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	@if $(PY) -m monolib.lockfile --usable; then \
		$(PY) -m pip install --quiet --no-compile --require-hashes --no-deps -r requirements.lock && \
		$(PY) -m pip install --quiet --no-compile --no-deps -e .; \
	else $(PY) -m pip install --quiet --no-compile -e '.[test]'; fi
	@# byte-compiled on every core (pip compiles on one: 40 s of a 2-core install); a file of another Python's syntax
	@# (torch ships a few for 3.12) fails here as pip lets it fail
	@$(PY) -m compileall -qq -j 0 $(VENV)/lib > /dev/null || true
	@if git rev-parse --git-dir >/dev/null 2>&1; then $(VENV)/bin/nbstripout --install --attributes .gitattributes; fi
	touch $(STAMP)

# requirements.lock from pip's resolution of pyproject.toml (nothing installed; the files' hashes from the index)
lock: install
	$(PY) -m pip install --dry-run --ignore-installed --quiet --report $(VENV)/lock-report.json -e '.[test]'
	$(PY) -m monolib.lockfile $(VENV)/lock-report.json requirements.lock

study: install
	$(VENV)/bin/monolib study $(STUDY)

# quick at the paper's training size (144 training settings x 60 frames, quick's test split; params/paper_scale.yaml
# -> figures/paper_scale/): about two hours on 2 cores, resumable (run it again after a stop), on the Dask cluster
# as any study (docs/cluster.md)
paper-scale: install
	$(VENV)/bin/monolib study paper_scale
	$(VENV)/bin/monolib training-size

# the training-size curve on both legs (figures/training_size.md, .png; figures/reproduces.md, the README's table):
# the middle sizes (params/quick_96x40.yaml, params/real_96x40.yaml; about an hour on 2 cores), read beside quick,
# paper_scale, real and real_full as committed (the development set unpacked as `make real` does: REAL_DATA)
training-size: install
	$(VENV)/bin/monolib unpack $(REAL_DATA) --out runs/published_graphs_dev
	$(VENV)/bin/monolib study quick_96x40
	$(VENV)/bin/monolib study real_96x40
	$(VENV)/bin/monolib training-size

# the result blocks of README.md and docs/*.md rewritten from figures/ (make study does it at its end)
readme: install
	$(PY) -c "from monolib.report import readme; readme.update()"

# docs/study-file.md, the study file's reference, rewritten from its schema in monolib/params.py
study-file-doc: install
	$(PY) -c "from monolib import study_file_doc; study_file_doc.write()"

# beyond the paper on the quick study's data (run `make study` first): encoder ablation, ours, depth scale
ablations: install
	$(VENV)/bin/monolib study ablations

# why the direction of the edges decides (run `make study` first): the paper's encoder against its 2 x 2 of direction
# and head at every threshold on scenarios 1 and 3, and along other node orders (params/direction.yaml)
direction: install
	$(VENV)/bin/monolib study direction

# the paper's question on real graphs: the published graphs' development set (REAL_DATA: its archive, or a folder
# with its train/) checked and unpacked into runs/published_graphs_dev/ (ignored), then cross-validated by volume at
# quick's training size (params/real.yaml -> figures/real/) and at its full size (params/real_full.yaml ->
# figures/real_full/). Resumable: run it again after a stop. docs/real-data.md
REAL_DATA ?= $(CURDIR)/../shared/data/published_graphs_dev.tar.xz
real: install
	$(VENV)/bin/monolib unpack $(REAL_DATA) --out runs/published_graphs_dev
	$(VENV)/bin/monolib study real
	$(VENV)/bin/monolib study real_full

# which property of the data sets what the edges cost: one property of one leg's graphs moved to the other leg's
# value at a time, both encoders trained again (params/data_edits.yaml -> figures/data_edits/; run `make direction`
# and `make real` first). Each leg on its own core, then the tables from both
data-edits: install
	$(VENV)/bin/monolib data-edits data_edits --leg mini & pid=$$!; \
	  $(VENV)/bin/monolib data-edits data_edits --leg real && wait $$pid
	$(VENV)/bin/monolib data-edits data_edits

# the node colour space (HDR against tonemapped) for gcn and ours in scenarios 1 and 3 (run `make study` first)
colour: install
	$(VENV)/bin/monolib study colour

# the from-scratch segmentation trained five times longer (run `make study` first)
perception-long: install
	$(VENV)/bin/monolib perception perception_long

# what ImageNet pretraining buys: quick's perception trained from scratch on quick's data (run `make study` first)
scratch: install
	$(VENV)/bin/monolib perception scratch

# after `make study`: the fresh figures against the committed ones (identical files, means moved against their
# committed 95% intervals, claims of params/claims.yaml that fail); exit 1 with one line per problem
verify: install
	$(VENV)/bin/monolib verify $(STUDY)

smoke: install
	$(VENV)/bin/monolib study smoke

# the model zoo: fine-tune the ImageNet-pretrained perception networks on their own mini-Hypersim (params/zoo.yaml)
# on the CPU, measure them on quick's test split after every epoch, write monolib/resources/zoo/<name>.pt + .json.
# Resumable per epoch: run it again after a stop. About an hour on 2 cores: `nohup make zoo > zoo.log &`
zoo: install
	$(VENV)/bin/monolib zoo zoo --eval quick

# the learning curve that sized make zoo (accuracy against CPU minutes at two sizes): figures/zoo_pilot.md
zoo-pilot: install
	$(VENV)/bin/monolib zoo zoo --eval quick --pilot

# tests/ first (they run the smoke study end to end), then every notebook with its smoke defaults (nbval, lax):
# every cell must run, and each cell marked # NBVAL_CHECK_OUTPUT must print what the committed notebook holds (its
# outputs survive the git filter through nbstripout's keep_output metadata, see notebooks/conftest.py). When a change
# moves those numbers on purpose: python tests/refresh_notebook_outputs.py, then review the diff.
# On TEST_WORKERS processes (pytest-xdist): the test files marked shares_runs (the checkout's runs/ folder) run on one of them in
# file order, the rest beside them (tests/conftest.py, `group_of`). TEST_WORKERS=0: one process.
test: install
	$(PY) -m pytest -n $(TEST_WORKERS) tests notebooks --nbval-lax --nbval-current-env --nbval-sanitize-with $(CURDIR)/tests/nbval_sanitize.cfg -p no:cacheprovider --durations=15

# the quick loop: ruff (pyproject.toml's [tool.ruff]), then the unit tests, without the tests marked slow (the smoke
# study, papermill, nbval, network training)
test-fast: install
	$(VENV)/bin/ruff check monolib tests notebooks
	$(PY) -m pytest tests -m "not slow" -p no:cacheprovider -q --durations=10

bench: install
	$(VENV)/bin/monolib bench frames --out figures/bench.json

# the grid's cells per minute: the local path and local Dask clusters of 1 and 2 workers (smoke study), and the
# paper study projected on 1, 8 and 64 workers from those per-cell costs
# where a grid cell's seconds go, on the finished quick study (figures/cell_profile.json and .md; about a minute)
bench-cell: install
	$(VENV)/bin/monolib bench cell --study quick --out figures/cell_profile.json
	$(PY) -c "from monolib.report import readme; readme.update()"  # the docs' copies of it

bench-grid: install
	$(VENV)/bin/monolib bench grid --out figures/scaling.json

# the dataset stage of quick rendered by the generator before version 5 (c736e94) and by this one, side by side
bench-render: install
	$(VENV)/bin/monolib bench render c736e94 --study quick --out figures/render_bench.json

# what a localizer of each method of the quick study costs (run `make study` first): database bytes per frame, ms per
# query image end to end, recall@1, side by side
bench-localizers: install
	$(VENV)/bin/monolib bench localizers --study quick --out figures/localizers.json
	$(PY) -c "from monolib.report import readme; readme.update()"  # the docs' copies of it

# the localizer on photos (run `make study` first): recall@1 of each method it offers when quick's test frames go
# through the photo path (JPEG quality 90, decoded, cropped, resized) against the same cells on the study's frames,
# and one image's latency end to end on one torch thread, median and p90: figures/localize.md and .csv
bench-localize: install
	$(VENV)/bin/monolib bench localize --study quick --out figures/localize.md
	$(PY) -c "from monolib.report import readme; readme.update()"  # the docs' copies of it

# one imagenet_triplet cell of the quick study (run `make study` first) with glibc's malloc as it is and with the
# project's (monolib.device.keep_freed_memory), in a new process each: seconds, system CPU, page faults, same files
bench-allocator: install
	$(VENV)/bin/monolib bench allocator --study quick --out figures/allocator.json

# how the trained encoders train and which epoch's model they keep (graph encoders, image_triplet, imagenet_triplet):
# the rules compared on the training split of the quick study (run `make study` first; resumable): figures/selection.md
bench-selection: install
	$(VENV)/bin/monolib bench selection --study quick

# the same rules at the development set's full training size, on fold 0's training side (after make real has
# unpacked it; resumable; about 75 minutes on 2 cores): figures/real_full/selection.md, the rule params/real_full.yaml trains by
bench-selection-real: install
	$(VENV)/bin/monolib bench selection --study real_full

# the measurement behind imagenet_vlad's whitening (none): recall@1 with and without it
bench-imagenet: install
	$(VENV)/bin/monolib bench imagenet --study quick --out figures/imagenet_choices.json

clean-runs:
	rm -rf runs/
