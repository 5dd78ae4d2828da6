# density-planner: two commands on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
CLI := $(VENV)/bin/density-planner
EXTRAS ?= mpc,commonroad,dask,dev,fast
comma := ,
STAMP := $(VENV)/.installed-$(subst $(comma),-,$(EXTRAS))
OUT ?= results
# test processes (pytest-xdist): the suite takes ~8.6 min on 2 and ~17 min on 1 on a slow 2-core machine (AMD EPYC,
# stop 59); TEST_WORKERS=0 runs it in this one process
TEST_WORKERS ?= 2

.PHONY: install demo test test-all bench lint clean

$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -c constraints.txt -e ".[$(EXTRAS)]"
	# byte-compile the package (an editable install does not; pip does for a regular one): where the environment
	# sets PYTHONDONTWRITEBYTECODE, every command would otherwise compile ~28 000 lines at start-up (~0.2 s)
	PYTHONDONTWRITEBYTECODE= $(PY) -m compileall -q src
	# compile the numba kernels once (nothing without the `fast` extra): the online controller's (~10 s), so that the
	# first `drive` does not pause for it, and the collision cost's (~4 s), so that the first plan does not
	$(PY) -m density_planner.control.fast
	$(PY) -m density_planner.cost._jit
	touch $(STAMP)

# the collision cost's kernels compiled ahead of time (~5 s; numba's pycc and a C compiler, else it says so and the
# just-in-time kernels above serve): a command then loads them in ~1 ms instead of importing numba (~0.5 s)
KERNELS := $(VENV)/.collision-kernels
$(KERNELS): $(STAMP) src/density_planner/cost/_jit.py src/density_planner/cost/_aot.py
	$(PY) -m density_planner.cost._aot
	touch $(KERNELS)

install: $(STAMP) $(KERNELS)

# the demo plans a recorded road scene that ships with the package (CommonRoad, BSD-licensed), default settings
DEMO_SCENARIO ?= src/density_planner/data/commonroad/USA_Lanker-1_1_T-1.xml

demo: $(STAMP) $(KERNELS)
	$(CLI) plan --env commonroad --file $(DEMO_SCENARIO) --out $(OUT)/demo
	@echo "Pictures: $(OUT)/demo/plan.png, $(OUT)/demo/plan.gif, $(OUT)/demo/costs.png (plan.json holds the numbers, solution.xml the CommonRoad solution)"

test: $(STAMP) $(KERNELS)
	$(PY) -m pytest -q -n $(TEST_WORKERS)

test-all: $(STAMP) $(KERNELS)
	$(PY) -m pytest -q -n $(TEST_WORKERS) -m ""

bench: $(STAMP) $(KERNELS)
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

lint: $(STAMP) $(KERNELS)
	$(PY) -m ruff check src tests benchmarks
	$(PY) -m mypy

clean:
	rm -rf $(VENV) build dist src/*.egg-info .pytest_cache src/density_planner/cost/_collision_aot_*
