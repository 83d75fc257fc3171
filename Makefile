# Everything runs from .venv, which the first target that needs it creates.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test check test-deps bench bench-peers samples clean vendor-js

$(STAMP): pyproject.toml
	@test -n "$(PYTHON)" || { echo "make: no python3.11 or python3 on PATH; install Python 3.11"; exit 2; }
	@$(PYTHON) -c 'import sys; sys.exit(sys.version_info < (3, 11))' || { echo "make: $(PYTHON) is older than Python 3.11"; exit 2; }
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	@touch $(STAMP)

# The whole tool on an embedded robot: simulator, recording proxy and a scripted
# client, live in the TUI, recorded to demo.mcap (--force: each run replaces the
# last).  Without a terminal (CI) it runs headless for a few seconds and prints
# the conformance report.
demo: $(STAMP)
	$(BIN)/whiztap demo --force

# Tests run in JOBS processes at once (pytest-xdist): two a core, as many tests
# wait on sockets, servers and other processes (a fresh clone on 2 cores: 4 took
# 210-218 s, 2 about 4 minutes; 6 took 203-228 s and made the tests that time a
# peer fail under the load; docs/benchmarks.md).  --dist worksteal lets an idle
# process take tests queued for a busy one, so they all end together (211 s
# where --dist load took 230 s).
JOBS ?= $(shell echo $$(( $$(nproc 2>/dev/null || echo 1) * 2 )))
DIST := -n $(JOBS) --dist worksteal

# Bytecode caches on for the tests, whatever the environment says: with
# PYTHONDONTWRITEBYTECODE set, each test process rewrites every test module's
# asserts again (7 s of collection each, 2.5 s with the cache) and each whiztap
# process a test starts compiles whiztap anew (docs/benchmarks.md, the test loop).
TEST_ENV := PYTHONDONTWRITEBYTECODE=

# Every test; each line of dots ends with how many have run, and the slowest
# are listed at the end.
test: $(STAMP) test-deps
	$(TEST_ENV) $(BIN)/pytest -q $(DIST) --durations=15

# The fast subset to run while you work: every test not marked slow (processes
# under load, Dask, tshark, soaks, memory bounds), in under a minute.
check: $(STAMP)
	$(TEST_ENV) $(BIN)/pytest -q $(DIST) -m "not slow"

# Debian and npm packages some tests use (tcpdump, socat, tshark, @mcap/core); idempotent.
test-deps:
	@bash .ci/install-test-deps

bench: $(STAMP) test-deps bench-peers
	$(BIN)/python -m benchmarks

# The peers the benchmarks compare with that pip installs: mitmproxy (mitmdump),
# in a venv of its own so its pins never meet whiztap's.  socat comes with test-deps.
bench-peers: .venv-peers/bin/mitmdump

.venv-peers/bin/mitmdump:
	$(PYTHON) -m venv .venv-peers
	.venv-peers/bin/pip install --quiet mitmproxy

samples: $(STAMP)
	$(BIN)/python samples/generate.py

clean:
	rm -rf $(VENV) .venv-peers .pytest_cache

# The uPlot the HTML report inlines, fetched again from the npm registry and
# checked against the SHA-256 of the file in the package (docs/analyze.md).
UPLOT := 1.6.32
UPLOT_SHA256 := 19c8d4c6ad88929a79f4ae49d6f7161566dfd0ba3d15cc495e974f787eb78f1f
vendor-js:
	@tmp=$$(mktemp -d) && cd $$tmp && npm pack --silent uplot@$(UPLOT) >/dev/null && tar xzf uplot-$(UPLOT).tgz && \
	  echo "$(UPLOT_SHA256)  package/dist/uPlot.iife.min.js" | sha256sum -c --quiet && \
	  cp package/dist/uPlot.iife.min.js package/dist/uPlot.min.css $(CURDIR)/analyzer/analysis/report/page-assets/ && \
	  cp package/LICENSE $(CURDIR)/analyzer/analysis/report/page-assets/uPlot.LICENSE && rm -rf $$tmp && echo "uPlot $(UPLOT) checked"
