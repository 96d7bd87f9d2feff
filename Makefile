# The two commands of README.md: `make demo` (main job) and `make test` (the suite).
# Each creates .venv and installs telebot into it first.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin

.PHONY: install install-debian demo test lint bench bench-quick clean

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev]'
	touch $@

demo: install
	$(BIN)/python -m telebot.apps.demo

lint: install
	$(BIN)/ruff check src tests bench
	$(BIN)/ruff format --check src tests bench
	$(BIN)/mypy

# --dist loadgroup: a module's tests that share a module-scoped daemon, router or browser run
# on one worker, which starts it once (tests/conftest.py schedules them); the rest load-balance.
# Three workers on two cores: the tests wait (on a robot that drives, a timeout, a browser)
# more than they compute; a fourth made it no faster.
# The quick benchmarks (tests/test_bench_quick.py, tests/test_bench_browser.py) run after the
# rest, two at a time: each starts several processes, and beside the browser tests they
# starved Chromium's video.
# The tests marked solo (pyproject.toml) load the whole machine on purpose (CPU burners, a
# flood); beside them a browser's call went silent for seconds: they run alone, after the rest.
# A step whose failures are few (at most RERUN_AT_MOST) runs those tests once more, one at a
# time, and fails if any fails again: on a busy 2-core machine a browser or multi-process
# test may miss a wait now and then. Both runs' failures are printed.
RERUN_AT_MOST := 10
QUICK_BENCHES := tests/test_bench_browser.py tests/test_bench_quick.py
NOT_QUICK_BENCHES := $(QUICK_BENCHES:%=--ignore=%)
RERUN_FAILED = { n=$$($(BIN)/python -c 'import json, pathlib; p = pathlib.Path(".pytest_cache/v/cache/lastfailed"); print(len(json.loads(p.read_text())) if p.exists() else 0)'); \
	echo "make test: $$n failed; at most $(RERUN_AT_MOST) are run again, one at a time"; \
	test "$$n" -ge 1 -a "$$n" -le $(RERUN_AT_MOST) && $(BIN)/pytest -q -rA --lf --lfnf=none; }
# This machine's environment sets PYTHONDONTWRITEBYTECODE: with no bytecode cache every
# pytest worker rewrote and compiled the hundred test modules again (10 s each time), and every
# process a test starts compiled telebot anew. An empty value turns it off for the tests.
test: export PYTHONDONTWRITEBYTECODE =
test: lint install-debian node_modules/.installed
	npm test
	rm -f .pytest_cache/v/cache/lastfailed  # a failure left by an earlier run is not this run's
	$(BIN)/pytest -n 3 --dist loadgroup -m "not solo" $(NOT_QUICK_BENCHES) || $(RERUN_FAILED)
	$(BIN)/pytest -q -m solo $(NOT_QUICK_BENCHES) || $(RERUN_FAILED)
	$(BIN)/pytest -q -n 2 $(QUICK_BENCHES) || $(RERUN_FAILED)

# The browser client's packages (package-lock.json): again only when the lockfile changed.
node_modules/.installed: package-lock.json | install-debian
	npm ci --no-audit --no-fund
	touch $@

# Every benchmark in full (tens of minutes); bench-quick runs each in its --quick mode
# (seconds each, tiny sizes: a check that none rots, its figures are noise), as
# tests/test_bench_quick.py does in `make test`.
BENCHES := channels nav mapxfer video safety fleet ros2 routers wan people record relay \
	ui media browser

bench: install install-debian
	set -e; for b in $(BENCHES); do $(BIN)/python bench/$$b.py; done

bench-quick: install install-debian
	set -e; for b in $(BENCHES); do $(BIN)/python bench/$$b.py --quick; done

install-debian:
	.ci/install-debian

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache .hypothesis
