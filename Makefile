# upright — one Makefile for setup, tests, demo, benchmarks and the firmware bundle.
# `make demo` and `make test` set themselves up on a fresh machine.

PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
NODE_STAMP := node_modules/.installed
OUT    ?= out
PORT   ?= /dev/ttyACM0
ARCH   ?= armv6m

.PHONY: all setup test demo bench fuzz soak firmware flash generate clean help rp2040 mutate dashboard-screenshot

all: test

help:
	@echo "make demo      set up, then run the main job and write plots to $(OUT)/"
	@echo "make test      set up, then run the test suite (TEST_JOBS=$(TEST_JOBS) workers)"
	@echo "make bench     speed figures, side by side in one run"
	@echo "make fuzz      the long fuzz run of the firmware frame decoder and command handler (>= 1M inputs)"
	@echo "make soak      one hour of simulated lockstep HIL: heap, timing drift, telemetry accounted for"
	@echo "make mutate    mutation check: small faults in a copy of the firmware, each must fail a test (not in make test)"
	@echo "make generate  regenerate the generated sources (gain tables, DBC, protocol docs)"
	@echo "make firmware  compile the firmware bundle with mpy-cross (ARCH=$(ARCH))"
	@echo "make flash     copy the bundle to a board (PORT=$(PORT)) with mpremote"
	@echo "make rp2040    build the emulated Pico's firmware (MicroPython rp2 port, Debian sources) into build/rp2040/"

setup: $(STAMP) $(NODE_STAMP) rp2040

$(STAMP): requirements.txt pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --disable-pip-version-check -q -r requirements.txt
	$(BIN)/pip install --disable-pip-version-check -q --no-deps --no-build-isolation -e .
	touch $@

# The 32-bit MicroPython WebAssembly port used by the allocation/small-int tests.
$(NODE_STAMP): package.json package-lock.json
	npm ci --no-audit --no-fund --loglevel=error
	touch $@

# The emulated board's firmware: MicroPython's rp2 port (RPI_PICO) built from Debian trixie
# sources with the machine's ARM toolchain, pinned and checksummed (docs/firmware.md).
# The apt step installs only the missing packages; `apt-get update` only if that fails.
# chromium: the dashboard's browser test (tests/test_dashboard_browser.py, playwright-core drives /usr/bin/chromium)
APT_PACKAGES := gcc-arm-none-eabi libnewlib-arm-none-eabi libstdc++-arm-none-eabi-newlib cmake make gcc libc6-dev debian-archive-keyring chromium
APT_STAMP    := build/.apt-installed
SUDO         := $(if $(filter 0,$(shell id -u)),,sudo)

rp2040: build/rp2040/firmware.bin

$(APT_STAMP): Makefile
	@missing=$$(for p in $(APT_PACKAGES); do \
	  dpkg-query -W -f='$${Status}\n' $$p 2>/dev/null | grep -q '^install ok installed' || echo $$p; done); \
	if [ -n "$$missing" ]; then \
	  echo "apt-get install" $$missing; \
	  $(SUDO) apt-get install -y --no-install-recommends $$missing || \
	  { $(SUDO) apt-get update && $(SUDO) apt-get install -y --no-install-recommends $$missing; }; \
	fi
	@mkdir -p $(@D) && touch $@

build/rp2040/firmware.bin: $(APT_STAMP) host/boards/rp2040/build.py host/boards/rp2040/manifest.py
	$(PYTHON) -m host.boards.rp2040.build
	touch $@

generate: $(STAMP)
	$(BIN)/upright generate

# The suite runs on TEST_JOBS workers (pytest-xdist), each test file on one worker (--dist loadfile:
# a file's tests share module fixtures and run in order); TEST_JOBS=0 runs it in this process.
# Two workers suit the 2-core CI machine (a board test is two processes taking turns, the
# firmware's and the plant's): 16 min against 28 min in one process on such a machine.
TEST_JOBS ?= 2

test: setup
	$(PY) -m pytest -q -n $(TEST_JOBS) --dist loadfile

demo: setup
	$(BIN)/upright demo --out $(OUT)

bench: setup
	$(PY) -m host.bench.main --out $(OUT)/bench.json

fuzz: setup
	$(PY) -m host.bench.main --only proto_fuzz fuzz_states --out $(OUT)/fuzz.json

soak: setup
	$(BIN)/upright soak --sim-seconds 3600

# deliberate faults in a temporary copy of the tree (never the working tree); exit 1 if one survives
mutate: $(STAMP) $(NODE_STAMP)
	$(PY) -m host.bench.mutate --json $(OUT)/mutate.json

firmware: $(STAMP)
	$(PY) -m host.boards.bundle --arch $(ARCH) --out $(OUT)/firmware

# checks within FLASH_TIMEOUT s that PORT is a MicroPython REPL (mpremote alone waits minutes, silent)
FLASH_TIMEOUT ?= 3
flash: firmware
	$(PY) -m host.boards.flash --port $(PORT) --bundle $(OUT)/firmware --mpremote $(BIN)/mpremote --timeout $(FLASH_TIMEOUT)

# the README's dashboard picture, taken by the browser test (headless Chromium, virtual board)
dashboard-screenshot: setup
	UPRIGHT_DASHBOARD_SCREENSHOT=docs/img/dashboard.png $(PY) -m pytest -q tests/test_dashboard_browser.py

clean:
	rm -rf $(OUT) .pytest_cache .hypothesis

# the design report as a notebook (docs/report.ipynb, committed without outputs), executed and rendered to HTML
.PHONY: report
report: $(STAMP)
	$(PY) -m nbconvert --to html --execute --ExecutePreprocessor.kernel_name=python3 --ExecutePreprocessor.timeout=600 \
	  --output-dir $(OUT)/report docs/report.ipynb
	@echo "report: $(OUT)/report/report.html"
