# btmission: `make demo` and `make test` do everything on a fresh machine.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test test-all test-slow install system-deps bench lint clean

# After installing, compile the numba kernels (D*+, GA, ray casting) once: ~25 s here, instead
# of in the middle of the first mission or test run (btmission/warmup.py).
$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test,viz,net,bench]"
	$(PY) -m btmission.warmup
	@touch $(STAMP)

install: $(STAMP) system-deps

# graphviz renders svg/png trees; chromium runs the viewer's browser tests. Installed when missing and possible (root + apt-get);
# otherwise a note, and every other feature keeps working (export to dot/xml/json/ascii).
system-deps:
	@command -v dot >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    echo "installing graphviz (svg/png export)..."; \
	    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq graphviz >/dev/null) \
	      || echo "note: could not install graphviz; svg/png export is unavailable"; \
	  else echo "note: graphviz 'dot' not found; svg/png export is unavailable (install graphviz)"; fi; }
	@command -v chromium >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    echo "installing chromium (the viewer's browser tests)..."; \
	    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) \
	      || echo "note: could not install chromium; the viewer's browser tests will be skipped"; \
	  else echo "note: chromium not found; the viewer's browser tests will be skipped (install chromium)"; fi; }

# The seed 000 field mission in the embedded simulator (tracking controller: ~10 s; drop
# --controller to fly the NMPC, about a minute); ends with its report (Tables III and II).
demo: install
	$(VENV)/bin/btmission run missions/mine_inspection.yaml --controller track --log runs

# The fast selection on every CPU (pytest-xdist; TEST_WORKERS=0 runs it in this process instead),
# then the tests paced by the wall clock (marked serial) alone, so that no other test slows them.
TEST_WORKERS ?= auto
test: install
	$(VENV)/bin/pytest -q -n $(TEST_WORKERS) --dist worksteal -m "not slow and not serial" --durations=15
	$(VENV)/bin/pytest -q -m "serial and not slow" --durations=5

test-all: install
	$(VENV)/bin/pytest -q -m ""

# The long end-to-end tests (missions on mavsim's MAVLink vehicles, the shipped missions ...).
test-slow: install
	$(VENV)/bin/pytest -q -m slow --durations=10

bench: install
	$(VENV)/bin/btmission bench synth

# ruff, mypy, and the layers of btmission/ (import-linter's contract in pyproject.toml;
# CONTRIBUTING.md says which layer new code goes in).
lint: install
	$(VENV)/bin/ruff check btmission cli library tests benchmarks
	$(VENV)/bin/ruff format --check btmission cli library tests benchmarks
	$(VENV)/bin/mypy btmission cli library
	$(VENV)/bin/lint-imports --no-cache

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
