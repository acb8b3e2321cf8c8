# Two commands: `make run` (one full default episode) and `make test` (the suite).
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
INTERFACE_SOURCES := $(shell find area3d_interfaces third_party/tf2_msgs -type f -not -name '*.md') \
	tools/build_interfaces.py tools/wheel_targets.cmake

.PHONY: install run test lint bench clean

# Foxglove's own WebSocket client, for the live-view test (versions locked in its package-lock.json)
FOXGLOVE_CLIENT := tests/foxglove_client

# The packages are installed by uv (pinned here; itself from the package index, into the venv),
# which resolves and unpacks them in parallel from its cache: 4-9 s where pip took 43 s on a
# 2-core machine. The bytecode is compiled at install (about 12 s on 2 cores): where
# PYTHONDONTWRITEBYTECODE is set, as on many CI and container images, none would ever be written,
# and every node process would compile numpy, scipy and rclpy from source again (0.9 s of CPU more
# per process; `make test` starts hundreds). The project's own modules are compiled with the
# kernels below. The venv keeps pip for packages a user adds (`.venv/bin/pip install ...`).
UV := $(VENV)/bin/uv
UV_VERSION := 0.13.9

$(STAMP): pyproject.toml $(FOXGLOVE_CLIENT)/package-lock.json
	$(PYTHON) tools/build_interfaces.py --check
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet uv==$(UV_VERSION)
	$(UV) pip install --quiet --compile-bytecode --python $(PY) -e ".[ros,dev,cluster]"
	@if command -v npm >/dev/null 2>&1; then \
		npm ci --prefix $(FOXGLOVE_CLIENT) --no-audit --no-fund --loglevel=error; \
	else \
		echo "npm not found: the Foxglove client test will be skipped (install Node.js to run it)"; \
	fi
	touch $(STAMP)

# The ROS 2 interfaces (tf2_msgs, area3d_interfaces) generated and built into the venv
# (tools/build_interfaces.py), and the numba kernels compiled into their on-disk cache, so that no
# node compiles one while the graph runs (area3d_bringup/kernels.py): the masks' kernels while the
# interfaces build, the two episodes' (which run the nodes' code, hence the interfaces) after,
# at once. Again
# when an interface, the build script, the venv's packages or a source file change: the interface
# build keeps a digest of its inputs and skips itself when nothing it depends on changed, and
# kernels already cached load in seconds.
BUILT := $(VENV)/.built
KERNEL_SOURCES := $(shell find area3d_* sim_bridge -name '*.py' -not -path '*/test/*')

$(BUILT): $(STAMP) $(INTERFACE_SOURCES) $(KERNEL_SOURCES)
	@$(PY) -m compileall -q -x '/test/' area3d_* sim_bridge tools >/dev/null
	@$(PY) -m area3d_bringup.kernels --part masks & masks=$$!; \
	$(PY) tools/build_interfaces.py && \
	$(PY) -m area3d_bringup.kernels --part camera --part stereo; built=$$?; \
	wait $$masks && test $$built -eq 0
	touch $(BUILT)

install: $(BUILT)

run: install
	$(VENV)/bin/area3d run

# Two test processes (pytest-xdist): most tests wait on node processes, DDS discovery and
# rendering, so two share a 2-core machine well (measured: 330 s against 600 s one at a time).
# Each process leases a ROS domain of its own (conftest.py). `make test TEST_WORKERS=0`: one.
# The longest tests are collected first (pyproject.toml) and an idle process takes queued tests
# from the other (`worksteal`): with plain `load`, the first quarter of the tests (the long ones)
# is dealt out up front and one process waited a minute or two on the other (measured: 331 s
# against 415 s, idle machine).
TEST_WORKERS ?= 2

test: install
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist worksteal

lint: install
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) runs build *.egg-info $(FOXGLOVE_CLIENT)/node_modules
