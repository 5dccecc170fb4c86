# The two commands of the README: `make run` (the demo) and `make test` (the tests).
# Each creates .venv and installs what it needs; system packages via scripts/install-system-deps.sh.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
# numba's loops compiled for this machine (`pointflow warm`): again when their source changes
WARMED := $(VENV)/.warmed
DURATION ?= 10
export XDG_RUNTIME_DIR ?= /tmp/pointflow-xdg-$(shell id -u)

.PHONY: run test bench system-deps clean

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip setuptools wheel
	$(BIN)/python -m pip install -q -e '.[test]'
	@touch $@

# compile ahead, where the set-up already waits: the demo then starts with the compiled raster
$(WARMED): $(STAMP) pointflow/render/cpu_kernels.py pointflow/frames/compiled.py
	@$(BIN)/pointflow warm && touch $@ || echo "warm: not cached (see above); runs draw with another tier while it compiles"

system-deps:
	@bash scripts/install-system-deps.sh

$(XDG_RUNTIME_DIR):
	@mkdir -p -m 700 $@

run: $(STAMP) $(WARMED) system-deps | $(XDG_RUNTIME_DIR)
	$(BIN)/pointflow run configs/demo.yaml --duration $(DURATION) --out out --record out/demo.mcap

# two workers (most tests wait on processes they started); TEST_JOBS=0 runs them in one process
TEST_JOBS ?= 2
test: $(STAMP) $(WARMED) system-deps | $(XDG_RUNTIME_DIR)
	$(BIN)/python -m pytest -q $(if $(filter-out 0,$(TEST_JOBS)),-n $(TEST_JOBS) --dist loadfile)

bench: $(STAMP) $(WARMED) system-deps | $(XDG_RUNTIME_DIR)
	for b in bench/bench_*.py; do $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) out .pytest_cache
