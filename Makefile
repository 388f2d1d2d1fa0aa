# Two commands a user needs: `make demo` and `make test`. Both create or reuse .venv.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test install notebooks bench clean

$(STAMP): setup.cfg pyproject.toml
	$(PYTHON) -m venv $(VENV)
	# torch==2.13.0 first: a bare `torch` requirement can pull a multi-GB CUDA build.
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e ".[cpu,test]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/open3d-pnerf demo --out out/demo

test: $(STAMP)
	$(PY) -m pytest -q

notebooks: $(STAMP)  # re-execute the notebooks (full runs, ~15 min) and save them with their outputs
	$(PY) notebooks/run_notebooks.py

bench: $(STAMP)  # needs ../shared/data; see benchmarks/README.md for the time each takes
	$(PY) benchmarks/bench_tracking.py
	$(PY) benchmarks/bench_targets.py
	$(PY) benchmarks/bench_nerf.py
	$(PY) benchmarks/bench_suite.py
	$(PY) benchmarks/bench_suite.py --datasets fern --budget 600 --name fern
	$(PY) benchmarks/bench_distributed.py
	$(PY) benchmarks/bench_pose_refinement.py
	$(PY) benchmarks/bench_memory.py

clean:
	rm -rf $(VENV) out
