# Both targets bootstrap .venv on their own; a second run reuses it.
PY      := python3
VENV    := .venv
VPY     := $(VENV)/bin/python
STAMP   := $(VENV)/.installed
LLVM_OK := $(VENV)/.llvm-ok

.PHONY: run test setup clean serve

setup: $(STAMP) $(LLVM_OK)

$(STAMP): pyproject.toml
	test -x $(VPY) || $(PY) -m venv $(VENV)
	$(VPY) -m pip install -q --upgrade pip
	# torch first and pinned: 2.13.0 resolves to the local CPU wheel; any other spec pulls CUDA.
	$(VPY) -m pip install -q torch==2.13.0
	$(VPY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

$(LLVM_OK):
	bash scripts/ensure-llvm.sh
	touch $(LLVM_OK)

test: setup
	# PostgreSQL for the job-store tests; without it those tests skip, the build goes on.
	bash scripts/ensure-postgres.sh || true
	$(VPY) -m pytest -q $(PYTEST_ARGS)

run: setup
	$(VENV)/bin/renderloop serve

clean:
	rm -rf $(VENV) out .pytest_cache
