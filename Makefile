# rgbdnav: the two fresh-machine commands are `make demo` and `make test`.
# Each creates .venv if missing, installs the system libraries (apt-get) and the project into it.

VENV        ?= .venv
PYTHON      ?= python3
PY          := $(VENV)/bin/python
STAMP       := $(VENV)/.rgbdnav-installed
APT_PACKAGES := libusb-1.0-0 libgomp1
DEMO_OUT    ?= runs/demo
PYTEST_ARGS ?=

.PHONY: setup demo test bench lint clean

$(STAMP): pyproject.toml
	@missing=""; for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing system packages:$$missing"; \
	  if [ "$$(id -u)" = 0 ]; then SUDO=""; elif command -v sudo >/dev/null; then SUDO=sudo; \
	  else echo "error: need root or sudo to apt-get install$$missing" >&2; exit 1; fi; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$missing >/dev/null; \
	fi
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@# uv resolves the same versions as pip and installs them in about a quarter of pip's time
	@# (open3d's wheel alone is 400 MB; docs/design/speed.md "Install"). pip does it if uv cannot
	@# reach its index (uv does not read pip.conf: a mirror configured only there).
	$(PY) -m pip install -q uv
	$(VENV)/bin/uv pip install -q --python $(PY) -e ".[dev]" || \
	  { $(PY) -m pip install -q --upgrade pip && $(PY) -m pip install -q -e ".[dev]"; }
	@touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/rgbdnav map scenes/house.yaml --out $(DEMO_OUT)

# The suite in two parts (docs/design/speed.md): all but the live runs on TEST_WORKERS
# pytest-xdist workers, then the live runs (marker `realtime`) alone, as they run against the wall
# clock. Both parts always run. pytest's exit code is kept in .venv/pytest-exit-code so .ci/run
# can tell "no tests" (5) apart: 5 only when neither part collected a test. Both parts share
# RGBDNAV_TEST_PASSES_DIR (tests/conftest.py `passes_dir`): inputs both need are made once.
TEST_WORKERS ?= 2
test: $(STAMP)
	@a=0; b=0; export RGBDNAV_TEST_PASSES_DIR=$$(mktemp -d); \
	$(PY) -X faulthandler -m pytest -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder \
	  -m "not realtime" $(PYTEST_ARGS) || a=$$?; \
	$(PY) -X faulthandler -m pytest -m realtime $(PYTEST_ARGS) || b=$$?; \
	rm -rf "$$RGBDNAV_TEST_PASSES_DIR"; \
	if [ $$a = 5 ] && [ $$b = 5 ]; then rc=5; elif [ $$a != 0 ] && [ $$a != 5 ]; then rc=$$a; \
	elif [ $$b != 0 ] && [ $$b != 5 ]; then rc=$$b; else rc=0; fi; \
	echo $$rc > $(VENV)/pytest-exit-code; exit $$rc

bench: $(STAMP)
	$(PY) bench/bench_simulator.py --out docs/benchmarks.md
	$(PY) bench/bench_readers.py --out docs/benchmarks.md
	$(PY) bench/bench_serial.py --out docs/benchmarks.md
	$(PY) bench/bench_sync.py --out docs/benchmarks.md
	$(PY) bench/bench_depth_to_scan.py --out docs/benchmarks.md
	$(PY) bench/bench_vo.py --out docs/benchmarks.md
	$(PY) bench/bench_pose_graph.py --out docs/benchmarks.md
	$(PY) bench/bench_mapper.py --out docs/benchmarks.md
	$(PY) bench/bench_house_route.py --out docs/benchmarks.md
	$(PY) bench/bench_localization.py --out docs/benchmarks.md
	$(PY) bench/bench_nav.py --out docs/benchmarks.md
	$(PY) bench/bench_live.py --out docs/benchmarks.md

lint: $(STAMP)
	$(VENV)/bin/ruff check sensors slam nav rgbdnav tests bench
	$(VENV)/bin/ruff format --check sensors slam nav rgbdnav tests bench
	$(VENV)/bin/mypy sensors slam nav rgbdnav

clean:
	rm -rf $(VENV) runs .pytest_cache
