# Two commands do everything on a fresh machine: `make demo` and `make test`.
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test bench clean

$(STAMP): pyproject.toml
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	# The CPU build of torch first, so the train extra pulls no CUDA packages.
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[dev,plots,vehicle,train,traffic,cluster,batched,ros]'
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/openconvoy demo

test: $(STAMP)
	$(VENV)/bin/ruff check openconvoy tests benchmarks
	$(VENV)/bin/ruff format --check openconvoy tests benchmarks
	$(VENV)/bin/mypy
	$(VENV)/bin/python -m pytest -q

bench: $(STAMP)
	for b in benchmarks/*.py; do $(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
