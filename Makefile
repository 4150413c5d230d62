# Every target does its own set-up: a fresh clone needs only Python 3.11+, make, (for
# the tests' InfluxDB server) Go and (for the OPC UA interoperability test) Node.js with npm.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

# The InfluxDB server the tests run against, built once from source and shared by every
# clone (tests/influxrig.py). Needs Go; ~2 minutes the first time.
INFLUXD_VERSION := 1.8.10
INFLUXD_CACHE   ?= $(HOME)/.cache/bench-supervisor/influxd-$(INFLUXD_VERSION)
INFLUXD         := $(INFLUXD_CACHE)/influxd

# The OPC UA client that is not asyncua (node-opcua-client), for the interoperability test:
# installed by npm from the committed lock file into a git-ignored folder.
INTEROP     := tests/interop
NODE_STAMP  := $(INTEROP)/node_modules/.installed

# The HMI's front-end libraries (uPlot), installed by npm from hmi/package-lock.json into
# the git-ignored hmi/node_modules: the supervisor serves them at /vendor/, never a CDN.
HMI_STAMP   := hmi/node_modules/.installed

# The browser tests' accessibility engine (axe-core), installed by npm from
# tests/browser/package-lock.json into the git-ignored tests/browser/node_modules: test
# tooling that Playwright injects into each screen, never served by the supervisor.
AXE_STAMP   := tests/browser/node_modules/.installed

# The browser the HMI's browser tests drive (tests/browser/): Debian's Chromium, never a
# browser downloaded by Playwright.
CHROMIUM    := /usr/bin/chromium
# The instruction counter of `supervisor bench pi-budget` (valgrind's callgrind): Debian's
# valgrind.
VALGRIND    := /usr/bin/valgrind
# The MQTT broker the Sparkplug B tests start on loopback (tests/mqttrig.py): Debian's
# mosquitto, never a service of the machine (each test starts its own on a free port).
MOSQUITTO   := /usr/sbin/mosquitto
SUDO        := $(if $(filter 0,$(shell id -u)),,sudo)

.PHONY: run demo-users test lint typecheck unit bench mutation schema check clean influxd node_modules hmi axe chromium valgrind

influxd: $(INFLUXD)

node_modules: $(NODE_STAMP)

$(NODE_STAMP): $(INTEROP)/package.json $(INTEROP)/package-lock.json
	@command -v npm >/dev/null || { echo "npm is required for the OPC UA interoperability test (node-opcua-client)"; exit 2; }
	cd $(INTEROP) && npm ci --no-audit --no-fund --loglevel=error
	touch $@

hmi: $(HMI_STAMP)

$(HMI_STAMP): hmi/package.json hmi/package-lock.json
	@command -v npm >/dev/null || { echo "npm is required to install the HMI's chart library (uPlot)"; exit 2; }
	cd hmi && npm ci --no-audit --no-fund --loglevel=error
	touch $@

axe: $(AXE_STAMP)

$(AXE_STAMP): tests/browser/package.json tests/browser/package-lock.json
	@command -v npm >/dev/null || { echo "npm is required for the browser tests' accessibility check (axe-core)"; exit 2; }
	cd tests/browser && npm ci --no-audit --no-fund --loglevel=error
	touch $@

chromium: $(CHROMIUM)

$(CHROMIUM):
	@echo "installing Debian's chromium for the HMI's browser tests"
	$(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y chromium \
	  || { $(SUDO) apt-get update && $(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y chromium; } \
	  || { echo "install the Debian package chromium (apt-get install chromium) for tests/browser/"; exit 2; }

valgrind: $(VALGRIND)

$(VALGRIND):
	@echo "installing Debian's valgrind for supervisor bench pi-budget"
	$(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y valgrind \
	  || { $(SUDO) apt-get update && $(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y valgrind; } \
	  || { echo "install the Debian package valgrind (apt-get install valgrind) for bench pi-budget"; exit 2; }

.PHONY: mosquitto
mosquitto: $(MOSQUITTO)

$(MOSQUITTO):
	@echo "installing Debian's mosquitto for the Sparkplug B tests"
	$(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y mosquitto \
	  || { $(SUDO) apt-get update && $(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y mosquitto; } \
	  || { echo "install the Debian package mosquitto (apt-get install mosquitto) for the Sparkplug tests"; exit 2; }

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "Python 3.11+ is required")'
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

## The simulated bench (io_maps/sim.yaml); Ctrl-C stops it with every output safe.
## First run: demo users viewer/viewer, operator/operator, engineer/engineer (DEMO ONLY).
run: $(STAMP) $(HMI_STAMP) demo-users
	$(BIN)/supervisor run io_maps/sim.yaml

# The three demo users of a simulated bench that has none yet (never on a real bench):
# `make demo-users BENCH=io_maps/load16.yaml`; `make run` makes those of io_maps/sim.yaml.
demo-users: BENCH ?= io_maps/sim.yaml
demo-users: $(STAMP)
	@users="$$($(BIN)/supervisor opcua list-users --io-map $(BENCH))" || exit 2; \
	if [ -z "$$users" ]; then \
	  for u in viewer operator engineer; do \
	    echo $$u | $(BIN)/supervisor opcua add-user $$u --role $$u --password-stdin --io-map $(BENCH) || exit 2; \
	  done; \
	  echo "demo users of $(BENCH) (demo only, never on a real bench): viewer/viewer operator/operator engineer/engineer"; \
	fi

## Lint, type-check and the whole test suite.
test: lint typecheck unit

# The complexity budget (tests/complexity.py): McCabe 12 and 60 lines a function, but for
# the allow-list tests/complexity_budget.txt, which only shrinks.
lint: $(STAMP)
	$(BIN)/ruff check supervisor tests
	$(BIN)/ruff format --check supervisor tests
	$(BIN)/lint-imports
	$(BIN)/python -m tests.complexity

typecheck: $(STAMP)
	$(BIN)/mypy

# The suite runs in three parts. The unit tests (virtual clock, CPU-bound) in TEST_JOBS
# processes (pytest-xdist); then the tests of real processes, sockets and browsers, also in
# TEST_JOBS processes — their wall time is spent waiting, not on a core — a module in one
# process (--dist loadfile: its supervisor, InfluxDB or browser is started once); last,
# alone, the tests marked "quiet": they assert that the scan kept its timing (no stall, no
# overrun) or run devices with sub-second timeouts in the test's own event loop.
TEST_JOBS ?= 2
PYTEST    := $(BIN)/pytest -q -n $(TEST_JOBS) --dist loadfile
WALL      := tests/integration tests/interop tests/security tests/browser

unit: $(STAMP) $(INFLUXD) $(NODE_STAMP) $(HMI_STAMP) $(AXE_STAMP) $(CHROMIUM) $(VALGRIND) $(MOSQUITTO)
	SUPERVISOR_INFLUXD=$(INFLUXD) $(PYTEST) tests/unit
	SUPERVISOR_INFLUXD=$(INFLUXD) $(PYTEST) -m "not quiet" $(WALL)
	SUPERVISOR_INFLUXD=$(INFLUXD) $(BIN)/pytest -q -m quiet $(WALL)

$(INFLUXD):
	@command -v go >/dev/null || { echo "Go is required to build the test InfluxDB server (influxd $(INFLUXD_VERSION))"; exit 2; }
	mkdir -p $(INFLUXD_CACHE)
	GOBIN=$(INFLUXD_CACHE) GOFLAGS=-buildvcs=false go install github.com/influxdata/influxdb/cmd/influxd@v$(INFLUXD_VERSION)

## Benchmarks: figures are printed, never asserted. Each figure of issue 13's table is
## also recorded (supervisor/bench/report.py) and the last step writes the table:
## var/bench/results.json and var/bench/results.md (figure | measured | target | reference
## | met?, with the machine), then issue 30's table. Every benchmark prints, beside its
## figures, the same run's reference: the hypervisor's steal while it ran and the
## pure-Python reference loop (10M additions) timed right after it; both are kept with its
## figures. BENCH_MEMORY_MIN=30 gives the 30-minute memory figure.
BENCH_DIR        ?= var/bench
BENCH_LOAD_S     ?= 60
BENCH_MEMORY_MIN ?= 3
BENCH_ENV        := SUPERVISOR_BENCH_RESULTS=$(BENCH_DIR)/results.jsonl SUPERVISOR_INFLUXD=$(INFLUXD)
bench: $(STAMP) $(INFLUXD) $(HMI_STAMP) $(CHROMIUM) $(VALGRIND) $(MOSQUITTO)
	mkdir -p $(BENCH_DIR) && rm -f $(BENCH_DIR)/results.jsonl
	$(BENCH_ENV) $(BIN)/supervisor bench scan --tags 1000 --period-ms 10 --seconds 10
	$(BENCH_ENV) $(BIN)/supervisor bench manual --hours 10
	$(BENCH_ENV) $(BIN)/supervisor bench dry-run --recipe recipes/nimh-25h-slow-cycle.yaml
	$(BENCH_ENV) $(BIN)/supervisor bench seed002
	$(BENCH_ENV) $(BIN)/supervisor bench faults
	# Issue 30's e-stop row: press -> every output safe p99 (target <= 25 ms).
	$(BENCH_ENV) $(BIN)/supervisor bench estop --presses 100 --period-ms 10
	$(BENCH_ENV) $(BIN)/supervisor bench kill-restart --iterations 20
	$(BENCH_ENV) $(BIN)/supervisor bench historian --tags 1000 --period-ms 10 --seconds 10
	$(BENCH_ENV) $(BIN)/supervisor bench influx --points 200000 --rounds 3
	$(BENCH_ENV) $(BIN)/supervisor bench opcua --clients 10 --seconds 10 --opcua-tags 50 --period-ms 50
	$(BENCH_ENV) $(BIN)/supervisor bench http --seconds 10 --http-clients 1
	# A flood under RLIMIT_NOFILE 1024: 2000 idle HTTP + 200 idle OPC UA connections, then
	# 100 wrong logins/s for 30 s; every device connected, no trip, no stall (issue 27).
	$(BENCH_ENV) $(BIN)/supervisor bench flood --flood-http 2000 --flood-opcua 200 --login-rate 100 --login-seconds 30
	# Issue 28: three 150 KB alias-amplified recipe texts posted at once by a viewer to
	# /api/recipes/validate: stalls, jitter p99 and RSS before/after, SIGTERM to exit.
	$(BENCH_ENV) $(BIN)/supervisor bench validate-attack
	# The load case (io_maps/load16.yaml): scan p99/period, overruns, jitter, GET /api/tags;
	# first the scan alone (the same map and recipes, every publisher off, ~100 s: issue
	# 30's reference), last the browse block (one OPC UA client browsing 10,000 nodes a
	# pass, GET /api/tags at 10/s: its overruns).
	$(BENCH_ENV) $(BIN)/supervisor bench load --seconds $(BENCH_LOAD_S)
	$(BENCH_ENV) $(BIN)/supervisor bench memory --minutes $(BENCH_MEMORY_MIN)
	# Issue 30: `supervisor check recipes/nimh-ds2710.yaml` wall time (median of fresh
	# processes), and the four-Chadèche bench's share of a Raspberry Pi 4 core
	# (instructions per scan counted by valgrind over a 60 s window, converted by published
	# Pi 4 Python runs).
	$(BENCH_ENV) $(BIN)/supervisor bench cli --runs 11
	$(BENCH_ENV) $(BIN)/supervisor bench pi-budget --seconds 60
	# Issue 35: 100 simulated benches (the real Sparkplug edge node, 100 tags each changing
	# every second) through one Mosquitto into the fleet: latency p50/p99, broker and fleet
	# CPU, fleet RSS, messages/s (about a minute with the births).
	$(BENCH_ENV) $(BIN)/supervisor bench fleet --benches 100 --seconds 30
	# The HMI in Chromium: update latency tag change -> page (p50/p99) and the page's weight
	# (tests/artifacts/hmi-figures.json).
	$(BIN)/pytest -q -s -p no:cacheprovider tests/browser -k "logs_in or update_latency"
	$(BENCH_ENV) $(BIN)/supervisor bench report --out $(BENCH_DIR)

## The mutation corpus (tests/mutation.py) through the real commands, one process each,
## one at a time per CPU: counts per class printed, every failure in var/mutation/report.md;
## exit 1 while a variant breaks the promise (a traceback, a timeout, a refusal without
## file:line:col, a certainly invalid file accepted). `make test` runs a sample in process.
MUTATION_N ?= 600
mutation: $(STAMP)
	$(BIN)/python -m tests.mutation_run $(MUTATION_N)

schema: $(STAMP)
	$(BIN)/supervisor schema --out .

## The fast inner loop, no server to build or start (no InfluxDB, no browser, no Node.js):
## lint, type-check, the shipped I/O maps and recipes through `supervisor check`, and the
## unit tests (tests/unit/) but the few marked integration. `make test` runs everything.
check: lint typecheck
	$(BIN)/supervisor check io_maps/*.yaml recipes/*.yaml
	$(PYTEST) -m "not integration" tests/unit

clean:
	rm -rf $(VENV) .mypy_cache .ruff_cache .pytest_cache $(INTEROP)/node_modules hmi/node_modules tests/browser/node_modules
