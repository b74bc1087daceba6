# aynamics — `make help` lists the targets.
SHELL := /bin/bash
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
MESA_PKGS := libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0 libosmesa6
export MUJOCO_GL ?= egl
export PYOPENGL_PLATFORM ?= egl

.PHONY: help setup mesa test test-slow test-all bench lint format train clean

help:  ## list the targets
	@grep -E '^[a-zA-Z_-]+:.*?## ' $(MAKEFILE_LIST) | awk 'BEGIN {FS = ":.*?## "}; {printf "  %-10s %s\n", $$1, $$2}'

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	# torch first: 2.13.0 is a CPU build on disk; anything else pulls GBs of CUDA wheels
	$(BIN)/pip install -q --disable-pip-version-check torch==2.13.0
	$(BIN)/pip install -q --disable-pip-version-check -e '.[dev]'
	@touch $(STAMP)

setup: $(STAMP) mesa  ## create .venv (torch==2.13.0 first) and install the package with dev extras

mesa:  ## install Debian's Mesa (EGL + OSMesa) for headless rendering when missing and running as root
	@missing=""; for p in $(MESA_PKGS); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -z "$$missing" ]; then exit 0; fi; \
	if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  echo "installing Mesa:$$missing"; \
	  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing >/dev/null) \
	    || echo "warning: could not install$$missing; OpenGL rendering tests will skip"; \
	else echo "note: Mesa packages missing ($$missing); not root, so OpenGL rendering tests will skip"; fi

test: setup  ## run the default test suite (offline, CPU)
	$(BIN)/python -m pytest -q -n 2 --dist loadfile

test-slow: setup  ## run the slow tests only
	$(BIN)/python -m pytest -q -m slow

test-all: setup  ## run every test, slow ones included
	$(BIN)/python -m pytest -q -m "not gpu"

bench: setup  ## run the benchmark scripts; they print measured figures and ratios
	@for f in benchmarks/bench_*.py; do echo "== $$f"; $(BIN)/python $$f || exit 1; done

TRAIN_DATA ?= data/generated/make_train_plain
TRAIN_SCENES ?= 1536
TRAIN_OUT ?= runs/make_train

train: setup  ## generate a small data set if missing, train the tiny model on the CPU (10-17 min once its data exist), print the validation table
	@# a data set simulated by older physics (simulate.PHYSICS_VERSION) or labelled by older code
	@# (generate.LABELS_VERSION: its scenes and texts) is moved aside, kept, and made again
	@if [ -f $(TRAIN_DATA)/dataset_dict.json ] && ! $(BIN)/python -c "import sys; from aynamics.dataset_store \
	  import stale_labels, stale_physics as p; sys.exit(bool(p('$(TRAIN_DATA)') or stale_labels('$(TRAIN_DATA)')))"; \
	  then old=$(TRAIN_DATA).old-$$(date +%Y%m%d-%H%M%S); mv $(TRAIN_DATA) $$old; \
	  echo "$(TRAIN_DATA) was made by older physics or labels: moved to $$old, generating it again"; fi
	@test -f $(TRAIN_DATA)/dataset_dict.json || $(BIN)/aynamics generate --num $(TRAIN_SCENES) --out $(TRAIN_DATA) \
	  --seed 0 --quiet width=112 height=80 backdrop=plain
	@# an earlier run there is moved aside, kept (train.py refuses a fresh run into a folder holding one)
	@if [ -e $(TRAIN_OUT) ]; then old=$(TRAIN_OUT).previous-$$(date +%Y%m%d-%H%M%S); mv $(TRAIN_OUT) $$old; \
	  echo "$(TRAIN_OUT) holds an earlier run: moved to $$old"; fi
	$(BIN)/python train.py experiment=make_train data.dir=$(TRAIN_DATA) hydra.run.dir=$(TRAIN_OUT)

lint: setup  ## ruff lint + format check
	$(BIN)/ruff check . && $(BIN)/ruff format --check .

format: setup  ## ruff autofix + format
	$(BIN)/ruff check --fix . && $(BIN)/ruff format .

clean:  ## remove caches (keeps .venv)
	rm -rf .pytest_cache .ruff_cache .hypothesis build *.egg-info
