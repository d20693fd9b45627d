# Two entry points on a fresh machine: `make demo` (the main job) and `make test`.
# Both create .venv, install torch 2.13.0 (CPU build, pinned) and build the native extension.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
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

demo: $(STAMP)
	$(PY) -m stereorepro demo

test: $(STAMP)
	$(PY) -m pytest -q -m "not slow" $(PYTEST_ARGS)

test-all: $(STAMP)
	$(PY) -m pytest -q $(PYTEST_ARGS)

bench: $(STAMP)
	$(PY) bench/reproject.py
	$(PY) bench/tracer.py
	$(PY) bench/stereo_cost.py
	$(PY) bench/moving_objects.py

clean:
	rm -rf build $(VENV) .pytest_cache
