# Both targets bootstrap .venv on their own; a second run reuses it.
PY      := python3
VENV    := .venv
VPY     := $(VENV)/bin/python
STAMP   := $(VENV)/.installed
LLVM_OK := $(VENV)/.llvm-ok

.PHONY: run test setup clean serve page-screenshot

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

# The page's browser tests need Chromium; where it cannot be installed they skip and say why.
test: setup
	# PostgreSQL for the job-store tests; without it those tests skip, the build goes on.
	bash scripts/ensure-postgres.sh || true
	bash scripts/ensure-chromium.sh || echo "renderloop: no Chromium; the page's browser tests will be skipped" >&2
	$(VPY) -m pytest -q $(PYTEST_ARGS)

run: setup
	$(VENV)/bin/renderloop serve

# docs/page.png: the page with a finished job, in headless Chromium (the slow-marked test).
page-screenshot: setup
	bash scripts/ensure-chromium.sh
	$(VPY) -m pytest -q -m slow tests/service/test_page_screenshot.py

clean:
	rm -rf $(VENV) out .pytest_cache
