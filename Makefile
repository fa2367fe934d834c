# dbw-applique: the two commands are `make demo` and `make test`; both set up what they need.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DEMO_SECONDS ?= 25
# Debian packages the tests need: for the vcan HIL tests user-mode Linux (+kmod, can-utils,
# iproute2), patchelf (for Debian testing's UML where bookworm's panics: CPUs with AMX) and,
# as the slow last resort, QEMU with busybox-static; systemd for `systemd-analyze verify`.
# tools/vcan_run.py fetches what is not a bookworm package (testing's UML) into ~/.cache.
HIL_DEBS := user-mode-linux kmod can-utils iproute2 patchelf qemu-system-x86 busybox-static
# chromium: the operator page's browser tests (Playwright drives Debian's /usr/bin/chromium;
# `playwright install` is never run).
TEST_DEBS := $(HIL_DEBS) systemd chromium
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: demo test venv debian-deps lint typecheck unit hil bench clean

demo: venv
	@echo "== dbw demo: the daemon on the built-in simulated vehicle for $(DEMO_SECONDS) s =="
	BIN=$(BIN) DEMO_SECONDS=$(DEMO_SECONDS) bash tools/demo.sh

test: debian-deps venv lint typecheck unit hil

venv: $(STAMP)

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "dbw-applique needs Python >= 3.11")'
	@$(PYTHON) -m venv --help >/dev/null 2>&1 || { \
	  echo "installing python3-venv"; $(SUDO) apt-get update -q && \
	  DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -q python3-venv; }
	@[ -x $(BIN)/python ] || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev]'
	@touch $(STAMP)

debian-deps:
	@missing=$$(for p in $(TEST_DEBS); do dpkg-query -W -f='$${Status}\n' $$p 2>/dev/null \
	  | grep -q 'install ok installed' || echo $$p; done); \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages:" $$missing; \
	  $(SUDO) apt-get update -q && \
	  DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -q --no-install-recommends $$missing; \
	fi

lint: venv
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/lint-imports

typecheck: venv
	$(BIN)/mypy

# The CPU-bound tests run on every core; the `realtime` ones (the daemon and its twins on
# the wall clock: tests/conftest.py marks them) one at a time, so none is starved by another.
UNIT_WORKERS ?= 2
unit: venv
	$(BIN)/pytest -n $(UNIT_WORKERS) -m "not vcan and not realtime" --durations=25
	$(BIN)/pytest -m realtime --durations=25

# Hardware-in-the-loop tests over real SocketCAN vcan: the host's, else user-mode Linux
# (Debian testing's, fetched, or the system's where that fails), else QEMU; chosen by probe.
# HIL_WAY=native|uml-system|uml-testing|qemu forces one.
HIL_WAY ?= auto
hil: venv debian-deps
	$(BIN)/python tools/vcan_run.py --way $(HIL_WAY)

bench: venv
	$(BIN)/python -m benchmarks.run

clean:
	rm -rf $(VENV) .mypy_cache .ruff_cache .pytest_cache .hypothesis .import_linter_cache .grimp_cache
