# Entry points on a fresh machine:
#   make demo          what the demo needs (.[experiment]: the tracer, EXR, figures, SSIM/FLIP), then `stereorepro demo`
#   make test          lint (ruff), the test suite (every extra), the docs site (warnings as errors), the install checks in
#                      fresh environments (.ci/test-install): what CI runs (.ci/run)
#   make               everything a contributor needs (.[dev]: every extra, pytest, mkdocs, ruff) in .venv
#   make test-suite    the test suite alone; make docs: the docs site alone (build/site); make test-install: the
#                      install checks alone
# Each creates .venv, installs torch $(TORCH_VERSION) first (pinned; pip finds the build its configuration points to:
# here the CPU wheel of its --find-links folder) and builds the native extension (editable install).
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
BASE_STAMP := $(VENV)/.installed-base
DEMO_STAMP := $(VENV)/.installed-demo
STAMP      := $(VENV)/.installed
# Blender as a module (bpy, for the tests against real Cycles renders) in its own environment: bpy 5.0.1 needs
# numpy < 2 and Python 3.11; where it cannot be installed the Blender tests are skipped.
BLENDER_VENV  := $(VENV)/blender
BLENDER_STAMP := $(BLENDER_VENV)/.installed
TORCH_VERSION ?= 2.13.0
PYTEST_ARGS ?=
SOURCES := pyproject.toml cpp_ext/CMakeLists.txt $(wildcard cpp_ext/src/*.cpp cpp_ext/src/*.h)

.DEFAULT_GOAL := venv
.PHONY: venv demo test test-suite test-install test-all docs lint bench clean

$(BASE_STAMP):
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q torch==$(TORCH_VERSION) "scikit-build-core>=0.10" "nanobind>=2.0"
	touch $@

# The demo's dependencies only. Without a C++ compiler the package installs without its native core (the torch and
# numpy paths run); --version says which.
$(DEMO_STAMP): $(SOURCES) | $(BASE_STAMP)
	$(PY) -m pip install -q --no-build-isolation -e ".[experiment]"
	$(VENV)/bin/stereorepro --version
	touch $@

# Everything, and the native core is required: the parity tests compare it with the torch paths.
$(STAMP): $(SOURCES) | $(BASE_STAMP)
	$(PY) -m pip install -q --no-build-isolation -e ".[dev]"
	$(PY) -c "import stereorepro, stereorepro._core as c; print('stereorepro', stereorepro.__version__, 'native core:', c.build_info())"
	touch $@ $(DEMO_STAMP)

venv: $(STAMP)

$(BLENDER_STAMP): | $(STAMP)
	test -x $(BLENDER_VENV)/bin/python || $(PYTHON) -m venv $(BLENDER_VENV)
	$(BLENDER_VENV)/bin/pip install -q "bpy==5.0.1" || echo "bpy is not installable here: the Blender tests will be skipped"
	touch $(BLENDER_STAMP)

demo: $(DEMO_STAMP)
	$(PY) -m stereorepro demo

test: lint test-suite docs test-install

test-suite: $(STAMP) $(BLENDER_STAMP)
	$(PY) -m pytest -q -m "not slow" $(PYTEST_ARGS)

# fresh throwaway environments: `pip install .` without a compiler (core only), `pip install '.[experiment]'` + demo
test-install:
	PYTHON=$(PYTHON) TORCH_VERSION=$(TORCH_VERSION) .ci/test-install

docs: $(STAMP)
	$(VENV)/bin/mkdocs build --strict

# ruff's lint rules of pyproject.toml and its formatter (check only) over the package, the tests, the benchmarks
# and the examples; `ruff format stereorepro tests bench examples` applies the format
lint: $(STAMP)
	$(VENV)/bin/ruff check stereorepro tests bench examples
	$(VENV)/bin/ruff format --check stereorepro tests bench examples

test-all: $(STAMP) $(BLENDER_STAMP)
	$(PY) -m pytest -q $(PYTEST_ARGS)

bench: $(STAMP)
	$(PY) bench/reproject.py
	$(PY) bench/tracer.py
	$(PY) bench/stereo_cost.py
	$(PY) bench/moving_objects.py

clean:
	rm -rf build $(VENV) .pytest_cache
