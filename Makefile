# Two commands: `make run` (one full default episode) and `make test` (the suite).
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# The ROS 2 interfaces (tf2_msgs, area3d_interfaces), generated and built into the venv.
INTERFACES := $(VENV)/.interfaces
INTERFACE_SOURCES := $(shell find area3d_interfaces third_party/tf2_msgs -type f -not -name '*.md') \
	tools/build_interfaces.py tools/wheel_targets.cmake

.PHONY: install run test lint bench clean

# Foxglove's own WebSocket client, for the live-view test (versions locked in its package-lock.json)
FOXGLOVE_CLIENT := tests/foxglove_client

# --no-compile: a module's bytecode is written when it is first imported, not for every module of
# every package at install (20 s of a fresh install: 62 -> 42 s measured, with pip's own upgrade).
$(STAMP): pyproject.toml $(FOXGLOVE_CLIENT)/package-lock.json
	$(PYTHON) tools/build_interfaces.py --check
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --no-compile -e ".[ros,dev,cluster]"
	@if command -v npm >/dev/null 2>&1; then \
		npm ci --prefix $(FOXGLOVE_CLIENT) --no-audit --no-fund --loglevel=error; \
	else \
		echo "npm not found: the Foxglove client test will be skipped (install Node.js to run it)"; \
	fi
	touch $(STAMP)

# Rebuilt when an interface, the build script or the venv's packages change (the script also
# keeps a digest of its inputs and skips the build when nothing it depends on changed).
$(INTERFACES): $(STAMP) $(INTERFACE_SOURCES)
	$(PY) tools/build_interfaces.py

# The numba kernels compiled into their on-disk cache, so that no node compiles one while the
# graph runs (area3d_bringup/kernels.py); again when a source file changes.
KERNELS := $(VENV)/.kernels
KERNEL_SOURCES := $(shell find area3d_* sim_bridge -name '*.py' -not -path '*/test/*')

$(KERNELS): $(INTERFACES) $(KERNEL_SOURCES)
	$(PY) -m area3d_bringup.kernels
	touch $(KERNELS)

install: $(KERNELS)

run: install
	$(VENV)/bin/area3d run

# Two test processes (pytest-xdist): most tests wait on node processes, DDS discovery and
# rendering, so two share a 2-core machine well (measured: 330 s against 600 s one at a time).
# Each process leases a ROS domain of its own (conftest.py). `make test TEST_WORKERS=0`: one.
TEST_WORKERS ?= 2

test: install
	$(PY) -m pytest -q -n $(TEST_WORKERS)

lint: install
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) runs build *.egg-info $(FOXGLOVE_CLIENT)/node_modules
