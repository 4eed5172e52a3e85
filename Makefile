# covers-dist: two commands for a new machine (Debian, Python 3.11):
#   make demo   install everything into .venv/ and train the demo (runs/demo)
#   make test   install everything into .venv/ and run the default test suite
# Which torch build (docs/guide/install.md): TORCH=pypi (default) installs PyPI's torch==2.13.0, which
# on Linux x86_64 is the CUDA build (it pulls several GB of nvidia-* wheels); TORCH=cuda is the
# same install, named for what it gives there; TORCH=cpu takes the CPU-only build from PyTorch's
# own index (TORCH_CPU_INDEX). To switch builds in an existing .venv: make clean-venv first.
SHELL := /bin/bash
PYTHON ?= python3.11
VENV := .venv
PIP := $(VENV)/bin/pip
STAMP := $(VENV)/.covers-dist-installed
TORCH ?= pypi
TORCH_VERSION := 2.13.0
TORCH_CPU_INDEX ?= https://download.pytorch.org/whl/cpu
ifeq ($(TORCH),cpu)
TORCH_PIP_ARGS := --index-url $(TORCH_CPU_INDEX)
else ifneq ($(filter $(TORCH),pypi cuda),)
TORCH_PIP_ARGS :=
else
$(error TORCH must be pypi, cuda or cpu (got '$(TORCH)'))
endif
export MUJOCO_GL ?= egl
export PYOPENGL_PLATFORM ?= egl
export RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER := 0

.PHONY: install demo test test-slow bench lint clean-venv

install: $(STAMP)

$(STAMP): requirements/lock.txt pyproject.toml scripts/install_system_deps.sh
	bash scripts/install_system_deps.sh
	test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade "pip>=24" wheel "setuptools>=68"
	$(PIP) install -q $(TORCH_PIP_ARGS) torch==$(TORCH_VERSION)
	$(PIP) install -q -r requirements/lock.txt
	$(PIP) install -q --no-deps --no-build-isolation -e .
	$(VENV)/bin/python -c "import covers_dist, escnn, metaworld, ray, ot, fastapi, torch; print('covers-dist installed in $(VENV)')"
	touch $(STAMP)

# trains COVERS on Drawer Close under D4 into runs/demo until it holds 0.9 on every transform or 6 min
# pass (a finished demo run is reused: --resume returns at once; one stopped by the time limit
# trains 6 min more); `covers-dist demo` is another thing: a toy image grid in runs/toy-grid
demo: install
	if [ -d runs/demo/checkpoints ]; then $(VENV)/bin/covers-dist train --resume runs/demo; \
	else $(VENV)/bin/covers-dist train --config configs/demo.yaml --run-dir runs/demo; fi
	$(VENV)/bin/covers-dist plot runs/demo

# two pytest-xdist workers, a test module each at a time, longest modules first (tests/conftest.py);
# PYTEST_WORKERS=0 runs the suite in this process only; PYTEST_ARGS adds options (e.g. --durations=25)
PYTEST_WORKERS ?= 2
PYTEST_ARGS ?=
test: install
	$(VENV)/bin/python -m pytest -n $(PYTEST_WORKERS) --dist loadfile --no-loadscope-reorder $(PYTEST_ARGS)

test-slow: install
	$(VENV)/bin/python -m pytest -m slow

bench: install
	$(VENV)/bin/covers-dist bench toy

clean-venv:
	rm -rf $(VENV)
