# `make demo` and `make test` work on a fresh machine with Python 3.11 and make:
# each creates .venv and installs what it needs.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install demo test lint format bench system-tools dashboards clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/hivemap demo

# Debian's docker-compose (v1) validates docker-compose.yml where no compose v2
# plugin exists, and with docker.io (dockerd) and debootstrap tests/test_compose.py
# builds and runs the compose deployment on a private engine; prometheus (with promtool) checks the scrape config and, in
# tests/test_prometheus.py, scrapes a running stack for real; chromium is the browser
# tests/test_viewer.py drives through playwright (which never downloads a browser of its
# own). Best effort: without root or apt the tests that need them say they skipped.
system-tools:
	@missing=""; \
	if ! docker compose version >/dev/null 2>&1 && ! command -v docker-compose >/dev/null 2>&1; then \
	  missing="$$missing docker-compose"; fi; \
	command -v dockerd >/dev/null 2>&1 || missing="$$missing docker.io"; \
	command -v debootstrap >/dev/null 2>&1 || missing="$$missing debootstrap"; \
	command -v ip >/dev/null 2>&1 || missing="$$missing iproute2"; \
	command -v promtool >/dev/null 2>&1 && command -v prometheus >/dev/null 2>&1 || missing="$$missing prometheus"; \
	command -v chromium >/dev/null 2>&1 || missing="$$missing chromium"; \
	if [ -n "$$missing" ] && command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then \
	  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
	     --no-install-recommends $$missing fonts-dejavu-core) \
	    >/dev/null 2>&1 || echo "note: could not install$$missing; their tests will skip"; \
	fi

# The Grafana dashboards are generated (services/dashboards.py, Grafana's foundation SDK);
# tests/test_deploy.py fails when the checked-in JSON is not what this writes.
dashboards: $(STAMP)
	$(BIN)/hivemap dashboards

# Two phases (tests/conftest.py says which tests are "serial" and why): the rest on two
# xdist workers, then the serial ones alone; both run even if the first fails.
test: $(STAMP) system-tools
	@$(BIN)/pytest -q -n 2 -m "not serial" --durations=15; a=$$?; \
	$(BIN)/pytest -q -m serial --durations=15; b=$$?; \
	if [ $$a -ne 0 ] || [ $$b -ne 0 ]; then exit 1; fi

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

format: $(STAMP)
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix .

bench: $(STAMP)
	$(BIN)/python bench/bench_demo.py

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
