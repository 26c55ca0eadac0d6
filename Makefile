# make demo / make test / make check work on a machine with only Python 3.11, pip and make:
# each creates .venv if missing and installs the pinned dependencies into it (every extra:
# requirements.lock, the runtime; requirements-dev.lock, tests, benchmarks and the build).
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: install test check demo bench browser clean

install: $(STAMP)

$(STAMP): pyproject.toml requirements.lock requirements-dev.lock
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements.lock -r requirements-dev.lock
	$(PY) -m pip install --quiet --no-deps --no-build-isolation -e .
	$(VENV)/bin/sdp warmup --quiet  # compiles and caches every kernel (~40 s): no command waits for it later
	touch $(STAMP)

# pytest-xdist workers: one per core (TEST_WORKERS=0: every test in this one process, as to debug one)
TEST_WORKERS ?= auto
XDIST := -n $(TEST_WORKERS) --dist loadgroup
# the tests' rewritten asserts and the modules' bytecode cached in __pycache__, where the environment
# says not to write it (PYTHONDONTWRITEBYTECODE): else each worker rewrites and compiles every test
# module again, some 3 s of each run's CPU per process
PYTEST := env -u PYTHONDONTWRITEBYTECODE $(PY) -m pytest

# the full suite (CI runs it)
test: $(STAMP)
	$(PYTEST) -q $(XDIST) --durations=20

# the quick tier while working: every module, no test marked slow (48-50 s on 2 cores, otherwise idle,
# 2026-12-03). Whole files per worker: a worker then loads only its files' kernels from Numba's cache
# (loadgroup, which spreads a file's tests over both, took 51-53 s in the same hour)
check: $(STAMP)
	$(PYTEST) -q -m "not slow" -n $(TEST_WORKERS) --dist loadfile --durations=20

# headless Chromium and its driver for the HTML report's browser test (tests/test_htmlreport.py), from
# the distribution's packages (Debian: chromium, chromium-driver); nothing to do when already there
browser:
	@if [ -x /usr/bin/chromium ] && [ -x /usr/bin/chromedriver ]; then echo "chromium: $$(/usr/bin/chromium --version 2>/dev/null)"; \
	else $$( [ "$$(id -u)" = 0 ] || echo sudo ) sh -c 'apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver'; fi

demo: $(STAMP)
	$(VENV)/bin/sdp demo -o demo-output

bench: $(STAMP)
	$(PY) benchmarks/bench_core.py

clean:
	rm -rf $(VENV) demo-output .pytest_cache
