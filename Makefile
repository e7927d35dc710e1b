# Two commands do all the set-up: `make demo` and `make test`.
PY      ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed
DEMO    ?= out/demo

.PHONY: venv test demo bench clean

venv: $(STAMP)

# torch==2.13.0 first: pip takes the local CPU wheel; everything after sees it satisfied.
$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q torch==2.13.0
	$(BIN)/pip install -q -e '.[dev,bench]'
	touch $(STAMP)

test: $(STAMP)
	$(BIN)/python -m pytest

demo: $(STAMP)
	$(BIN)/fmapping demo --out $(DEMO)

# Hours on 2 CPU cores: every benchmark, then the README table (bench/report.py).
BENCHES := field_micro transport tracking mapping slam system faults real
bench: $(STAMP)
	for b in $(BENCHES); do $(BIN)/python bench/$$b.py || exit 1; done
	$(BIN)/python bench/mapping.py --real-data
	$(BIN)/python bench/report.py

clean:
	rm -rf $(VENV) out .pytest_cache
