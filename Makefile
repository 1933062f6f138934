# Two commands on a fresh machine: `make forest` and `make test`.
# Each creates (or reuses) .venv and installs what it needs from pyproject.toml.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
# the physics engine the collider tests drive (newton, CPU); its own venv because its USD
# importer pins usd-core. Optional: without it those tests skip and say why.
PHYS       ?= .venv-physics
PHYS_STAMP := $(PHYS)/.installed
# NVIDIA's asset validator (usd-validation-nvidia), also in its own venv for the same reason
CHECK       ?= .venv-validate
CHECK_STAMP := $(CHECK)/.installed
# Blender as a Python module (bpy), to import the forest as a Blender user does
BLENDER       ?= .venv-blender
BLENDER_STAMP := $(BLENDER)/.installed
# pytest processes (pytest-xdist), each running whole test files so that a file's own
# forests are built once (forests several files read are built once a run, tests/forestcache.py):
# `make test TEST_JOBS=1` runs them one after another
TEST_JOBS ?= 2
PYTEST    := $(BIN)/python -m pytest -q -n $(TEST_JOBS) --dist loadfile

.PHONY: forest test test-quick test-durations lint bench figures templates docs clean

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "usdforest needs Python >= 3.11")'
	@echo "== installing usdforest and its dependencies into $(VENV) (first time: a few minutes, 1.6 GB)"
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --progress-bar on -e '.[dev]'
	@echo "== installed: run $(BIN)/usdforest, or 'source $(BIN)/activate' for plain usdforest"
	touch $(STAMP)

forest: $(STAMP)
	$(BIN)/usdforest build forest.usda --force

$(PHYS_STAMP):
	@echo "== installing the physics engine the collider tests drive into $(PHYS) (newton, 2.1 GB; optional)"
	-test -x $(PHYS)/bin/python || $(PYTHON) -m venv $(PHYS)
	-$(PHYS)/bin/python -m pip install --progress-bar on 'newton[importers]>=1.8' && touch $(PHYS_STAMP)

$(CHECK_STAMP):
	@echo "== installing NVIDIA's asset validator into $(CHECK) (0.2 GB; optional)"
	-test -x $(CHECK)/bin/python || $(PYTHON) -m venv $(CHECK)
	-$(CHECK)/bin/python -m pip install --progress-bar on 'usd-validation-nvidia>=1.22' usd-core && touch $(CHECK_STAMP)

$(BLENDER_STAMP):
	@echo "== installing Blender as a Python module into $(BLENDER) (bpy, 1.0 GB; optional)"
	-test -x $(BLENDER)/bin/python || $(PYTHON) -m venv $(BLENDER)
	-$(BLENDER)/bin/python -m pip install --progress-bar on 'bpy>=4.2' && touch $(BLENDER_STAMP)

SIDE_ENVS := USDFOREST_PHYSICS_PYTHON=$(abspath $(PHYS))/bin/python \
	USDFOREST_BLENDER_PYTHON=$(abspath $(BLENDER))/bin/python \
	USDFOREST_NVIDIA_VALIDATE=$(abspath $(CHECK))/bin/nvidia_usd_validate

# the whole suite, with the three side environments (installed the first time)
test: $(STAMP) $(PHYS_STAMP) $(CHECK_STAMP) $(BLENDER_STAMP)
	@echo "== the whole test suite (14-30 minutes on 2 cores, by the machine; make test-quick: 4-10)"
	$(SIDE_ENVS) $(PYTEST)

# the inner loop: no side environments, no shipped forest, no test measured at 5 s or more
# (tests/durations.json); the tests that need a side environment skip and say so
test-quick: $(STAMP)
	$(PYTEST) -m "not heavy"

# the whole suite, then tests/durations.json (what test-quick leaves out, the files' order)
test-durations: $(STAMP) $(PHYS_STAMP) $(CHECK_STAMP) $(BLENDER_STAMP)
	$(SIDE_ENVS) $(PYTEST) --durations=50 --junitxml=.pytest-durations.xml
	$(BIN)/python tests/durations.py .pytest-durations.xml

lint: $(STAMP)
	$(BIN)/ruff check usdforest tests benchmarks templates docs pipelines

templates: $(STAMP)
	$(BIN)/python templates/make_cad.py
	$(BIN)/usdforest template build pipelines/templates.toml --force

docs: $(STAMP)
	$(BIN)/sphinx-build -W --keep-going -q -b html docs docs/_build/html
	@echo "== the documentation site: docs/_build/html/index.html"

figures: $(STAMP)
	$(BIN)/python docs/make_figures.py docs/figures

bench: $(STAMP) $(BLENDER_STAMP)
	$(BIN)/python benchmarks/run.py
	$(BIN)/python benchmarks/bench_raytrace.py
	USDFOREST_BLENDER_PYTHON=$(abspath $(BLENDER))/bin/python $(BIN)/python benchmarks/bench_lod.py
	$(BIN)/python benchmarks/bench_startup.py
	$(BIN)/python benchmarks/bench_flight.py
	$(BIN)/python benchmarks/bench_surveys.py
	$(BIN)/python benchmarks/bench_floor.py
	$(BIN)/python benchmarks/bench_leaves.py
	$(BIN)/python benchmarks/bench_wind.py
	$(BIN)/python benchmarks/bench_tiles.py 1 10
	$(BIN)/python benchmarks/bench_spatstat.py
	$(BIN)/python benchmarks/bench_stats.py
	$(BIN)/python benchmarks/bench_inventory.py

clean:
	rm -rf $(VENV) $(PHYS) $(CHECK) $(BLENDER) build *.egg-info .pytest_cache forest.usda forest_assets
