# Two commands for a newcomer: `make run` (the main job) and `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin

$(BIN)/tryon: pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[test]'
	@touch $@

.PHONY: setup run test bench clean
setup: $(BIN)/tryon

run: setup
	$(BIN)/tryon session --out out

test: setup
	$(BIN)/python -m pytest -q tests

bench: setup
	$(BIN)/python bench/bench_body.py
	$(BIN)/python bench/bench_body.py --every 2
	$(BIN)/python bench/bench_cloth.py
	$(BIN)/python bench/bench_surface.py
	$(BIN)/python bench/bench_bus.py

clean:
	rm -rf $(VENV) out
