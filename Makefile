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

# The tests drive PostgreSQL, Chromium, Ray, pyoidn and the Landlock wall for real: make installs
# what it can, and a test whose component is still missing fails, naming it and how to install it
# (tests/required_components.py). ALLOW_SKIP=1 (`make test ALLOW_SKIP=1`), for machines that cannot
# have one, skips those tests instead and says why.
ALLOW_SKIP ?=
test: setup
	bash scripts/ensure-postgres.sh || true
	bash scripts/ensure-chromium.sh || true
	ALLOW_SKIP=$(ALLOW_SKIP) $(VPY) -m pytest -q $(PYTEST_ARGS)

run: setup
	$(VENV)/bin/renderloop serve

# docs/page.png: the page with a finished job, in headless Chromium (the slow-marked test).
page-screenshot: setup
	bash scripts/ensure-chromium.sh
	$(VPY) -m pytest -q -m slow tests/service/test_page_screenshot.py

clean:
	rm -rf $(VENV) out .pytest_cache
