# The two commands: `make run` and `make test`. Both create .venv when needed.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: run test bench peers paper clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

# pip's output goes to a log, shown only if the install fails. Then, as pip does for a
# regular install, the bytecode is compiled, and so is every Numba kernel (`elimfast cache
# warm`, one to a few minutes), so that the first `make run` loads them and starts at once.
WARM = $(BIN)/python -m compileall -q elimfast cli && $(BIN)/elimfast cache warm

$(VENV)/.installed: pyproject.toml | $(BIN)/python
	@echo "installing elimfast and its dependencies into $(VENV) (pip, quiet; its log: $(VENV)/install.log) ..."
	$(BIN)/python -m pip install --quiet -e . > $(VENV)/install.log 2>&1 || (cat $(VENV)/install.log; exit 1)
	$(WARM)
	touch $@

$(VENV)/.installed-test: pyproject.toml | $(BIN)/python
	@echo "installing elimfast with its test extras into $(VENV) (pip, quiet; its log: $(VENV)/install.log) ..."
	$(BIN)/python -m pip install --quiet -e '.[test]' > $(VENV)/install.log 2>&1 || (cat $(VENV)/install.log; exit 1)
	$(WARM)
	touch $(VENV)/.installed $@

run: $(VENV)/.installed
	$(BIN)/elimfast run configs/kepler.yaml -o out/kepler.h5 --overwrite --quiet
	$(BIN)/elimfast inspect out/kepler.h5

test: $(VENV)/.installed-test
	$(BIN)/python -m pytest -q

paper: $(VENV)/.installed
	$(BIN)/elimfast paper --out paper-out --overwrite

bench: $(VENV)/.installed-test
	$(BIN)/python bench/kernel.py
	$(BIN)/python bench/end_to_end.py
	$(BIN)/python bench/sweep.py
	$(BIN)/python bench/sweep_dask.py --dask
	$(BIN)/python bench/sweep_xarray.py --out bench/results/sweep_xarray.md
	$(BIN)/python bench/user_problem.py
	$(BIN)/python bench/ensemble.py
	$(BIN)/python bench/adaptive_vs_fixed.py --markdown bench/results/adaptive_vs_fixed.md

# Comparison with scipy, REBOUND and heyoka (the optional bench extra).
peers: $(BIN)/python
	$(BIN)/python -m pip install --quiet -e '.[test,bench]' > $(VENV)/install.log 2>&1 || (cat $(VENV)/install.log; exit 1)
	$(BIN)/python bench/peers.py

clean:
	rm -rf $(VENV) build *.egg-info
	find . -name __pycache__ -type d -prune -exec rm -rf {} +
