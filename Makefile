# `make demo` and `make test` are what a user needs; both create or reuse .venv.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# THREADS=n runs the tests on n torch/OpenMP threads (make test THREADS=1); unset, the machine's cores
RUN := $(if $(THREADS),OMP_NUM_THREADS=$(THREADS) ,)$(PY)

.PHONY: demo test test-slow docs install notebooks bench clean

$(STAMP): setup.cfg pyproject.toml
	$(PYTHON) -m venv $(VENV)
	# torch==2.13.0 first: a bare `torch` requirement can pull a multi-GB CUDA build.
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e ".[cpu,test,docs]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/open3d-pnerf demo --out out/demo

test: $(STAMP)  # the fast suite, a few minutes: unit, analytic and small real-pipeline tests
	$(RUN) -m pytest -q -m "not slow"

test-slow: $(STAMP)  # the end-to-end tests: notebooks, data-parallel ranks, kernel builds, real data (~8 min)
	$(RUN) -m pytest -q -m slow

docs: $(STAMP)  # the documentation site (site/), API reference from the docstrings; fails on any warning
	$(VENV)/bin/mkdocs build --strict --quiet

notebooks: $(STAMP)  # re-execute the notebooks (full runs, ~15 min) and save them with their outputs
	$(PY) notebooks/run_notebooks.py

bench: $(STAMP)  # needs ../shared/data; docs/benchmarks.md says what each answers and how long it takes
	$(PY) benchmarks/bench_demo.py --runs 3
	$(PY) benchmarks/bench_map.py
	$(PY) benchmarks/bench_losses.py
	$(PY) benchmarks/bench_tracking.py
	$(PY) benchmarks/bench_speed.py

clean:
	rm -rf $(VENV) out site
