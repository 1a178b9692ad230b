# Two commands do all the set-up on a fresh machine:
#   make study   creates .venv/, installs the project, runs the default (quick) study and writes figures/
#   make test    creates .venv/, installs the project, runs the whole test suite (pytest + nbval)
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
STUDY ?= quick
export MPLBACKEND := agg
export PYTHONHASHSEED := 0

.PHONY: install study ablations perception-long smoke test bench clean-runs

install: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	@if git rev-parse --git-dir >/dev/null 2>&1; then $(VENV)/bin/nbstripout --install --attributes .gitattributes; fi
	touch $(STAMP)

study: install
	$(VENV)/bin/monolib study $(STUDY)

# beyond the paper on the quick study's data (run `make study` first): encoder ablation, ours, depth scale
ablations: install
	$(VENV)/bin/monolib study ablations

# the quick study's segmentation trained about three times longer (run `make study` first)
perception-long: install
	$(VENV)/bin/monolib perception perception_long

smoke: install
	$(VENV)/bin/monolib study smoke

# tests/ first (they run the smoke study end to end), then every notebook with its smoke defaults (nbval, lax)
test: install
	$(PY) -m pytest tests notebooks --nbval-lax --nbval-current-env --nbval-sanitize-with $(CURDIR)/tests/nbval_sanitize.cfg -p no:cacheprovider --durations=15

bench: install
	$(VENV)/bin/monolib bench --out figures/bench.json

clean-runs:
	rm -rf runs/
