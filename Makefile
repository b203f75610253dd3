# Two commands do everything on a fresh Debian machine with Python 3.11:
#   make demo   install into .venv (and Debian packages when root), then run the demo
#   make test   install, then lint (ruff), type-check (mypy) and run the test suite
PYTHON ?= python3.11
VENV   ?= .venv
PY      = $(VENV)/bin/python
DEMO_OUT ?= out/bunny
# Vulkan (lavapipe) and X libraries for GGUI; chromium for the browser viewer's tests (Playwright drives the system browser)
DEB_PACKAGES = mesa-vulkan-drivers libvulkan1 libgl1 libegl1 libxrender1 libxi6 libxkbcommon0 libsm6 libxxf86vm1 libxfixes3 chromium

.PHONY: install deps demo lint test bench clean

$(VENV)/.installed: pyproject.toml
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "error: $(PYTHON) not found; whitecap needs Python 3.11 (bpy 5.0 requires it)" >&2; exit 1; }
	@$(MAKE) --no-print-directory deps
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[render,usd,cluster,web,test]"
	@touch $@

deps:
	@if [ "$$(id -u)" = "0" ]; then \
		missing=""; for p in $(DEB_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
		if [ -n "$$missing" ]; then echo "installing Debian packages:$$missing"; \
			apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $$missing >/dev/null; fi; \
	else \
		for p in $(DEB_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || { \
			echo "note: Debian package $$p is missing and this is not root; run: sudo apt-get install $(DEB_PACKAGES)" >&2; break; }; done; \
	fi

install: $(VENV)/.installed

demo: install
	$(VENV)/bin/whitecap run scenes/bunny.toml --out $(DEMO_OUT) --preview

# ruff's rules and mypy's module list are in pyproject.toml
lint: install
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy

test: install lint
	$(PY) -m pytest -q tests

bench: install
	$(PY) benchmarks/bench_solver.py

clean:
	rm -rf $(VENV) out .pytest_cache .mypy_cache .ruff_cache
