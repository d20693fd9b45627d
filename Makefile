# Two entry points on a fresh machine: `make demo` (the main job) and `make test`.
# Both create .venv, install torch 2.13.0 (CPU build, pinned) and build the native extension.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
# Blender as a module (bpy, for the tests against real Cycles renders) in its own environment: bpy 5.0.1 needs
# numpy < 2 and Python 3.11; where it cannot be installed the Blender tests are skipped.
BLENDER_VENV  := $(VENV)/blender
BLENDER_STAMP := $(BLENDER_VENV)/.installed
TORCH_VERSION ?= 2.13.0
PYTEST_ARGS ?=

.PHONY: venv demo test test-all bench clean

$(STAMP): pyproject.toml cpp_ext/CMakeLists.txt $(wildcard cpp_ext/src/*.cpp)
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q torch==$(TORCH_VERSION) "scikit-build-core>=0.10" "nanobind>=2.0"
	$(PY) -m pip install -q --no-build-isolation -e ".[test]"
	$(PY) -c "import stereorepro, stereorepro._core as c; print('stereorepro', stereorepro.__version__, 'native core:', c.build_info())"
	touch $(STAMP)

venv: $(STAMP)

$(BLENDER_STAMP): | $(STAMP)
	test -x $(BLENDER_VENV)/bin/python || $(PYTHON) -m venv $(BLENDER_VENV)
	$(BLENDER_VENV)/bin/pip install -q "bpy==5.0.1" || echo "bpy is not installable here: the Blender tests will be skipped"
	touch $(BLENDER_STAMP)

demo: $(STAMP)
	$(PY) -m stereorepro demo

test: $(STAMP) $(BLENDER_STAMP)
	$(PY) -m pytest -q -m "not slow" $(PYTEST_ARGS)

test-all: $(STAMP) $(BLENDER_STAMP)
	$(PY) -m pytest -q $(PYTEST_ARGS)

bench: $(STAMP)
	$(PY) bench/reproject.py
	$(PY) bench/tracer.py
	$(PY) bench/stereo_cost.py
	$(PY) bench/moving_objects.py

clean:
	rm -rf build $(VENV) .pytest_cache
