# Two commands: `make run` (one full default episode) and `make test` (the suite).
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: install run test lint bench clean

# Foxglove's own WebSocket client, for the live-view test (versions locked in its package-lock.json)
FOXGLOVE_CLIENT := tests/foxglove_client

$(STAMP): pyproject.toml $(FOXGLOVE_CLIENT)/package-lock.json
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[ros,dev]"
	@if command -v npm >/dev/null 2>&1; then \
		npm ci --prefix $(FOXGLOVE_CLIENT) --no-audit --no-fund --loglevel=error; \
	else \
		echo "npm not found: the Foxglove client test will be skipped (install Node.js to run it)"; \
	fi
	touch $(STAMP)

install: $(STAMP)

run: install
	$(VENV)/bin/area3d run

test: install
	$(PY) -m pytest -q

lint: install
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) runs build *.egg-info $(FOXGLOVE_CLIENT)/node_modules
