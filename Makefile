# `make test` and `make search` each create .venv and install what they need.
# torch is pinned by constraints.txt to the CPU build on this machine's disk; on a GPU machine,
# point CONSTRAINTS at your own file (e.g. `make search CONSTRAINTS=gpu-constraints.txt`).
PYTHON ?= python3
VENV ?= .venv
CONSTRAINTS ?= constraints.txt
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-$(notdir $(CONSTRAINTS))
SEARCH_ARGS ?=

.PHONY: test test-fast search install benchmarks docs clean browser

$(STAMP): pyproject.toml $(CONSTRAINTS)
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -c $(CONSTRAINTS) -e ".[test]"
	touch $(STAMP)

install: $(STAMP)

# The tests run in one process per core (pytest-xdist; at most 4, which the slowest file bounds anyway),
# each given whole files so that a module's fixtures are built once. TEST_WORKERS=0 runs them in this one.
TEST_WORKERS ?= $(shell n=$$(nproc 2>/dev/null || sysctl -n hw.ncpu 2>/dev/null || echo 1); [ $$n -gt 4 ] && n=4; echo $$n)
PYTEST := $(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile

test: $(STAMP) browser
	$(PYTEST)

# the tests without the end-to-end ones (marked slow): a couple of minutes
test-fast: $(STAMP)
	$(PYTEST) -m "not slow"

# the documentation site, in build/site (the tests build it too, with --strict)
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/python -m mkdocs build --strict

# The report test opens the HTML in headless Chromium (Debian's package); skipped if it cannot be had.
browser:
	@command -v chromium >/dev/null 2>&1 || { apt-get update -q && apt-get install -y -q chromium; } >/dev/null 2>&1 \
		|| echo "chromium could not be installed: the browser test will be skipped"

# `make search` keeps to SEARCH_LIMIT_S in all: the time the setup took comes out of the search's
# --time-limit (unless SEARCH_ARGS sets --time-limit or --timeout itself). STARTED is read when make starts.
SEARCH_LIMIT_S ?= 960
STARTED := $(shell date +%s)
OWN_LIMIT := $(findstring --time-limit,$(SEARCH_ARGS))$(findstring --timeout,$(SEARCH_ARGS))

search: $(STAMP)
	@left=$$(( $(SEARCH_LIMIT_S) - $$(date +%s) + $(STARTED) )); [ $$left -ge 300 ] || left=300; \
	limit="$(if $(OWN_LIMIT),,--time-limit $$left)"; \
	echo "$(BIN)/explorer search --device tx2 $$limit $(SEARCH_ARGS)"; \
	$(BIN)/explorer search --device tx2 $$limit $(SEARCH_ARGS)

# the suites that fit a CPU in reasonable time; each says what it skips (GPU runs, whole commands)
benchmarks: $(STAMP)
	for s in runtime training search commands gpu; do $(BIN)/python -m benchmarks.$$s --cpu || exit 1; done

clean:
	rm -rf $(VENV) .cache .pytest_cache build
