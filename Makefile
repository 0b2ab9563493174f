VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# Debian packages the tests use: cmake and g++ (prime_msgs built in the ROS 2 client environments, as colcon
# would), check_urdf, a browser for the view, cyclictest, which the 1 kHz benchmark runs after its loop to
# measure the machine's own real-time latency, and stress-ng, which loads the cores for the tests that must hold
# on a busy robot computer.
TEST_DEBS := g++ cmake liburdfdom-tools chromium rt-tests stress-ng libcap2-bin
ROS_DEBS := g++ cmake
BENCH_DEBS := rt-tests
# The install compiles the tick kernels (Cython): a C compiler, and Python's headers where they are missing.
PY_INCLUDE := $(shell python3 -c "import sysconfig; print(sysconfig.get_paths()['include'])")
BUILD_DEBS := gcc $(if $(wildcard $(PY_INCLUDE)/Python.h),,python3-dev)

# The suite's parallel workers (docs/development.md, Tests): two real-time lanes, each running the real-time tests one
# at a time (they mostly wait on the wall clock: one lane alone takes longer than the rest of the suite), and a worker
# a core for the rest.
TEST_WORKERS ?= $(shell echo $$(( $$(nproc) + 2 )))
PRIME_SUITE_REALTIME_LANES ?= 2
export PRIME_SUITE_REALTIME_LANES

.PHONY: sim test typecheck bench soak lint clean ros

$(STAMP): pyproject.toml setup.py $(wildcard src/humanoid_prime/*/*.pyx src/humanoid_prime/*/*/*.pyx)
	tools/install-debs $(BUILD_DEBS)
	python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	# Bytecode compiled once here: where PYTHONDONTWRITEBYTECODE is set, every command would compile the package
	# again at each start (`prime bench --only startup` says which).
	$(PY) -m compileall -q src/humanoid_prime
	touch $(STAMP)

sim: $(STAMP)
	$(VENV)/bin/prime sim

test: $(STAMP) ros
	tools/install-debs $(TEST_DEBS)
	$(MAKE) lint typecheck
	$(PY) -m pytest -q -n $(TEST_WORKERS)

lint: $(STAMP)
	$(VENV)/bin/ruff check src tests

# mypy, strict over the package (pyproject.toml's [tool.mypy] names the modules that wait); stubtest holds the
# compiled kernels' stubs (_tick.pyi) to the built modules, so a changed kernel signature fails here rather than at a
# caller.
TICK_MODULES := humanoid_prime.control._tick humanoid_prime.drivers.ethercat._tick humanoid_prime.drivers.sito._tick
typecheck: $(STAMP)
	$(PY) -m mypy
	$(PY) -m mypy.stubtest $(TICK_MODULES) --mypy-config-file pyproject.toml --allowlist tools/stubtest-allowlist \
		--ignore-disjoint-bases

bench: $(STAMP)
	tools/install-debs $(BENCH_DEBS)
	$(VENV)/bin/prime bench

# ROS 2 clients from PyPI's wheels (Jazzy, Kilted), each in a venv of its own under ~/.cache/prime with Prime and its
# extra installed and prime_msgs and interfaces/ built in it: the environments the DDS tests use (tests/dds/conftest.py's
# ros_clients), so `make test` builds them before the suite starts, once; a look-up of a fraction of a second after.
ros: $(STAMP)
	tools/install-debs $(ROS_DEBS)
	$(PY) tools/ros-venv jazzy kilted

soak: $(STAMP)
	$(VENV)/bin/prime bench soak

clean:
	rm -rf $(VENV) build src/*.egg-info .pytest_cache
	find src \( -name '*.so' -o -name '*.c' \) -delete
