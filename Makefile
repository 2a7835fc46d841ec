# edgecal: the two commands of the README.
#   make demo   render data, detect, calibrate, stream pose from a replay
#   make test   make lint, then the test suite (CI runs exactly this)
#   make lint   ruff (style, imports, docstrings) and mypy (types)
# Both create (or reuse) the virtualenv .venv and install what they need, Debian packages included.

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
# Debian packages the tests need (the Aravis fake camera, libdc1394, systemd-analyze, PyGObject's build deps;
# PyGObject and pycairo are built from source, so Debian's python3 also needs its headers and venv).
SYSTEM_PACKAGES ?= aravis-tools aravis-tools-cli gir1.2-aravis-0.8 libgirepository1.0-dev libcairo2-dev pkg-config libdc1394-25 systemd python3-dev python3-venv

.PHONY: demo test lint typecheck bench system-deps clean

# order-only: `make demo` builds PyGObject too, so it needs the Debian packages first (without forcing a reinstall)
$(VENV)/.installed: pyproject.toml | system-deps
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 10) else "edgecal needs Python 3.10 or newer")'
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,aravis]'
	touch $@

system-deps:
	@missing=""; for p in $(SYSTEM_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages:$$missing"; \
	  SUDO=""; [ "$$(id -u)" = 0 ] || SUDO=sudo; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$missing; \
	fi

demo: $(VENV)/.installed
	$(VENV)/bin/edgecal demo --out out/demo --force

test: system-deps $(VENV)/.installed lint
	$(PY) -m pytest -q

lint: $(VENV)/.installed
	$(VENV)/bin/ruff check .
	@$(MAKE) --no-print-directory typecheck

# mypy follows no import hooks, so it cannot see that drivers/ is installed as edgecal.drivers: it checks a tree of
# links with the installed layout (build/typecheck/edgecal/, drivers/ inside it; its messages name those paths).
TYPECHECK := build/typecheck
typecheck: $(VENV)/.installed
	@rm -rf $(TYPECHECK) && mkdir -p $(TYPECHECK)/edgecal
	@for f in edgecal/*; do ln -s "$(CURDIR)/$$f" $(TYPECHECK)/edgecal/; done
	@ln -s "$(CURDIR)/drivers" $(TYPECHECK)/edgecal/drivers
	cd $(TYPECHECK) && $(abspath $(PY)) -m mypy --config-file "$(CURDIR)/pyproject.toml" \
	  --cache-dir "$(CURDIR)/build/mypy_cache" -p edgecal

bench: $(VENV)/.installed
	$(PY) -m pip install --quiet -e '.[bench]'
	$(PY) -m pip install --quiet --no-deps checkerboard
	$(PY) bench/detect.py

clean:
	rm -rf $(VENV) out build *.egg-info
