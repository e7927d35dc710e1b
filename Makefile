# Two commands do all the set-up: `make demo` and `make test`.
PY      ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed
DEMO    ?= out/demo

.PHONY: venv lint test test-fast demo bench clean

venv: $(STAMP)

# torch==2.13.0 first: pip takes the local CPU wheel; everything after sees it satisfied.
$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q torch==2.13.0
	$(BIN)/pip install -q -e '.[dev,bench]'
	touch $(STAMP)

# ruff (pyproject.toml [tool.ruff]) first, then every test, the slow ones included
lint: $(STAMP)
	$(BIN)/ruff check fmapping services tests bench examples

test: lint
	$(BIN)/python -m pytest

# the same without the tests marked slow (each over ~10 s here)
test-fast: lint
	$(BIN)/python -m pytest -m "not slow"

demo: $(STAMP)
	$(BIN)/fmapping demo --out $(DEMO)

# Hours on 2 CPU cores: every benchmark, then the README table (bench/report.py).
BENCHES := field_micro transport tracking mapping init_speed slam system tracker_realtime faults real long_run export_memory
bench: $(STAMP)
	for b in $(BENCHES); do $(BIN)/python bench/$$b.py || exit 1; done
	$(BIN)/python bench/system.py --poses gt --fps 0 10 --out bench/results/system_gt.json
	$(BIN)/python bench/mapping.py --real-data
	$(BIN)/python bench/report.py

clean:
	rm -rf $(VENV) out .pytest_cache
