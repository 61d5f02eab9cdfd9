# Two promises: `make demo` and `make test` work on a fresh clone.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
export PYOPENGL_PLATFORM ?= egl

.PHONY: demo test test-slow lint bench venv clean

venv: $(STAMP)

# torch is installed first and pinned so nothing pulls a CUDA build. onnx2torch (white-box ONNX)
# without its dependencies: it lists torchvision, whose registry wheels are CUDA builds that do
# not load against the CPU torch (see pyproject.toml); its real ones (numpy, onnx, torch) are ours.
# yourdfpy (URDF arms) likewise: it lists trimesh[easy], mesh-loading extras sim.kinematics never uses;
# what it imports (lxml, six, numpy, trimesh) is ours.
$(STAMP): pyproject.toml Makefile
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q --no-deps onnx2torch==1.5.15
	$(PY) -m pip install -q --no-deps yourdfpy==0.0.60
	$(PY) -m pip install -q -e ".[dev,ray]"
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/advobj demo --out runs/demo

test: $(STAMP)
	$(PY) -m pytest -q

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow

clean:
	rm -rf $(VENV) runs
