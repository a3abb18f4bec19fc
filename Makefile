# StarlETH simulator: developer entry points.
PYTHON ?= python3
VENV   := .venv
VPY    := $(VENV)/bin/python
PIP    := $(VPY) -m pip -qq --disable-pip-version-check --no-input
STAMP  := $(VENV)/.installed
PYTEST_ARGS ?=
LIVE_PORT ?= 8765

.PHONY: venv test-deps robots test sanitize sanitizer-libs format demo bench eval ray browser-test constraints \
        ros2-control-configs clean distclean

venv: $(STAMP)

# Creates .venv (reusing an existing one). With a sourced ROS 2 install providing
# rclpy, the venv sees the system site-packages and the ROS wheels are skipped;
# otherwise the ROS 2 Jazzy PyPI wheels from requirements-ros.txt are installed.
# (What only the tests and the benchmarks need comes with `make test-deps`.)
# Then the optional live view's requirements-live.txt (foxglove-sdk: sim_node live_view,
# starleth-demo --live); where it fails to install, the venv goes on without the live view.
# Then the ROS 2 interface packages that have no wheel (tf2_msgs: /tf and /tf_static on DDS),
# generated from venv_interfaces/ with the rosidl generator wheels of
# requirements-interfaces.txt (venv_interfaces/generate.py; nothing to do where an installed
# ROS provides them); where that fails, one line says so and the venv goes on.
# The top-level package __init__ files are prerequisites because the editable
# install only maps top-level packages that existed when it ran.
$(STAMP): requirements.txt requirements-ros.txt requirements-live.txt \
          requirements-interfaces.txt constraints.txt setup.py setup.cfg package.xml \
          venv_interfaces/generate.py venv_interfaces/wheel_include_dirs.cmake \
          $(wildcard venv_interfaces/*/package.xml venv_interfaces/*/CMakeLists.txt venv_interfaces/*/msg/*.msg) \
          $(wildcard starleth_sim/__init__.py starleth_controller/__init__.py starleth_interface/__init__.py)
	@set -e; \
	if [ ! -x $(VPY) ]; then \
	  if $(PYTHON) -c 'import rclpy' >/dev/null 2>&1; then \
	    echo "venv: system rclpy found, creating $(VENV) with --system-site-packages"; \
	    $(PYTHON) -m venv --system-site-packages $(VENV); \
	  else \
	    echo "venv: creating $(VENV)"; \
	    $(PYTHON) -m venv $(VENV); \
	  fi; \
	fi; \
	if $(VPY) -c 'import rclpy' >/dev/null 2>&1; then \
	  echo "venv: rclpy importable, skipping requirements-ros.txt"; \
	else \
	  echo "venv: installing ROS 2 Jazzy wheels (requirements-ros.txt)"; \
	  $(PIP) install -c constraints.txt -r requirements-ros.txt; \
	fi; \
	echo "venv: installing requirements.txt requirements-live.txt"; \
	$(PIP) install -c constraints.txt -r requirements.txt; \
	$(PIP) install -c constraints.txt -r requirements-live.txt || \
	  echo "venv: the live view's optional requirements-live.txt failed to install: no live view"; \
	$(VPY) venv_interfaces/generate.py || true; \
	echo "venv: installing starleth_sim (editable)"; \
	$(PIP) install -e . --no-deps; \
	touch $@

# What the tests need beyond the venv (requirements-test.txt: pytest, colcon, ray, MuJoCo for
# the benchmark's comparison, ruff); `make test` installs it, `make demo` does not.
TEST_STAMP := $(VENV)/.test-installed
test-deps: $(TEST_STAMP)

$(TEST_STAMP): $(STAMP) requirements-test.txt requirements-bench.txt constraints.txt
	@echo "test-deps: installing requirements-test.txt"
	@$(PIP) install -c constraints.txt -r requirements-test.txt
	@touch $@

# The robot library's URDFs beyond StarlETH (requirements-robots.txt: example-robot-data,
# about 415 MB installed), for the robots of robots/*.yaml (Simulator.from_preset(...,
# robot="go1")) and their tests; `make test` installs them, `make venv` and `make demo` do not.
ROBOTS_STAMP := $(VENV)/.robots-installed
robots: $(ROBOTS_STAMP)

$(ROBOTS_STAMP): $(STAMP) requirements-robots.txt constraints.txt
	@echo "robots: installing requirements-robots.txt (example-robot-data)"
	@$(PIP) install -c constraints.txt -r requirements-robots.txt
	@touch $@

# Per-run ROS_DOMAIN_ID (10..99) so concurrent runs on one host do not cross-talk.
# First the kernels ready (starleth-precompile: the three C extensions of a source checkout,
# the physics kernels, the controller's kernels and sim_node's command parsers, a few seconds
# the first time, then nothing): else both pytest workers would wait for the same build. Then two passes (test/conftest.py says which test goes where):
# pass 1 on two pytest-xdist workers, one running the tests that start ROS nodes one after
# another while the other runs the CPU-bound tests file by file; pass 2, the tests marked
# serial (rates, deadlines, latencies, a browser), one at a time with nothing beside them.
# Both list what they skipped, with the reason (-rs: an optional package or program missing);
# a missing rclpy is no skip but an error (test/conftest.py; STARLETH_ALLOW_NO_ROS=1 allows it).
# Then the physics tests that take every kernel path (SANITIZE_QUICK) under AddressSanitizer
# and UndefinedBehaviorSanitizer (make sanitize runs all of them, about 2 minutes), skipped
# with a line where the compiler's runtimes are missing. Then ruff over the tree (ruff.toml)
# and clang-format over the C files (.clang-format).
# All passes run; the target fails with the first failing pass's status (a pytest pass's 5,
# no tests collected, only if neither pass collected any: a -k selection may fall in one pass
# alone).
test: venv test-deps robots
	@export ROS_DOMAIN_ID=$$(( $$$$ % 90 + 10 )); \
	$(VPY) -m starleth_sim.tools.precompile --jobs 2 || echo "(precompile failed: the tests compile what they need and say what is wrong)"; \
	echo "pass 1: 2 workers: the ROS node tests one by one beside the CPU-bound tests"; \
	$(VPY) -m pytest -q -rs -n 2 --ros-apart -m "not serial" test \
	  $(PYTEST_ARGS); a=$$?; \
	echo "pass 2: tests marked serial (rates, deadlines), one at a time"; \
	$(VPY) -m pytest -q -rs -m serial test $(PYTEST_ARGS); b=$$?; \
	echo "pass 3: the physics kernels under AddressSanitizer + UBSan (SANITIZE_QUICK; all: make sanitize)"; \
	if [ -e "$$($${CC:-cc} -print-file-name=libasan.so)" ] && [ -e "$$($${CC:-cc} -print-file-name=libubsan.so)" ]; then \
	  $(MAKE) --no-print-directory sanitize SANITIZE_TESTS="$(SANITIZE_QUICK)" PYTEST_ARGS=; d=$$?; \
	else echo "SKIPPED: the compiler's libasan / libubsan are not installed (make sanitizer-libs)"; d=0; fi; \
	echo "pass 4: ruff check (ruff.toml), the C files' format (.clang-format; make format fixes it)"; \
	$(VENV)/bin/ruff check .; c=$$?; \
	$(VENV)/bin/clang-format --dry-run --Werror $(C_FILES) || c=1; \
	if [ $$a = 5 ] && [ $$b = 0 ]; then a=0; fi; \
	if [ $$b = 5 ] && [ $$a = 0 ]; then b=0; fi; \
	if [ $$a != 0 ]; then exit $$a; fi; if [ $$b != 0 ]; then exit $$b; fi; \
	if [ $$d != 0 ]; then exit $$d; fi; exit $$c

# The main job: the trotting demo over ROS 2 (starleth-demo; it makes the kernels ready
# first, with a progress line, then runs sim_node + controller_node and summarises the bag),
# with the live view (--live: the URL to open in Foxglove is printed) where foxglove-sdk
# (requirements-live.txt) is installed, on port LIVE_PORT (make demo LIVE_PORT=9000; 8765 by
# default); a busy port only turns the live view off.
demo: venv
	@if $(VPY) -c 'import foxglove' >/dev/null 2>&1; then \
	  echo "demo: foxglove-sdk installed: with the live view (starleth-demo --live $(LIVE_PORT))"; \
	  $(VENV)/bin/starleth-demo --live $(LIVE_PORT); \
	else \
	  echo "demo: no live view (pip install -r requirements-live.txt for it)"; \
	  $(VENV)/bin/starleth-demo; \
	fi

# starleth-bench, then the side-by-side comparison with MuJoCo (requirements-bench.txt, an
# optional dependency installed here only), then what a fresh clone's first run builds
# (starleth-precompile --cold: each unit's seconds and the total)
bench: venv
	$(PIP) install -r requirements-bench.txt
	$(VENV)/bin/starleth-bench
	$(VENV)/bin/starleth-bench --vs-mujoco
	$(VENV)/bin/starleth-precompile --cold --jobs 2

eval: venv
	$(VENV)/bin/starleth-eval

# the optional Ray extra (starleth-sweep / starleth-eval --ray auto|local|ADDRESS)
ray: venv
	$(PIP) install -c constraints.txt -e '.[ray]'

# starleth-view's HTML in a real browser (test/tools/test_view.py -k browser): installs Debian's
# chromium with apt when it is missing (sudo when not root, non-interactive), then runs only
# the browser tests; they render the replay with SwiftShader (no GPU, no display needed).
browser-test: venv
	@set -e; \
	if ! command -v chromium >/dev/null 2>&1; then \
	  SUDO=; [ "$$(id -u)" -eq 0 ] || SUDO=sudo; \
	  echo "browser-test: installing chromium with apt-get"; \
	  $$SUDO env DEBIAN_FRONTEND=noninteractive apt-get update -q; \
	  $$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -q chromium; \
	fi
	$(VPY) -m pytest -q test/tools/test_view.py -k browser -rs $(PYTEST_ARGS)

# Refresh constraints.txt on purpose: the newest versions the requirements resolve to, in a
# throw-away venv (then run `make test` with them and commit constraints.txt).
constraints:
	@set -e; tmp=$$(mktemp -d); \
	$(PYTHON) -m venv $$tmp/venv; \
	$$tmp/venv/bin/python -m pip -q --disable-pip-version-check --no-input install \
	  -r requirements-ros.txt -r requirements.txt -r requirements-test.txt -r requirements-live.txt \
	  -r requirements-interfaces.txt -r requirements-robots.txt; \
	{ echo "# Exact versions the test suite passed with (Python $$($$tmp/venv/bin/python -c 'import sys; print("%d.%d" % sys.version_info[:2])'), $$(date +%Y-%m-%d)); make installs with"; \
	  echo "# -c constraints.txt. Refresh on purpose with \`make constraints\` (a fresh venv from the"; \
	  echo "# requirements files without constraints), then run \`make test\` and commit both."; \
	  $$tmp/venv/bin/python -m pip freeze --disable-pip-version-check; } > constraints.txt; \
	rm -rf $$tmp; echo "constraints.txt refreshed: run make test, then commit it"

# Regenerate config/<robot>_controllers.yaml (ros2_control controllers) of every library robot
# from its URDF (test/ros/test_ros2_control_files.py checks they are up to date).
ros2-control-configs: venv robots
	@set -e; for r in $$($(VPY) -c 'from starleth_sim.robots import available_robots as a; print(*a())'); do \
	  $(VPY) -m starleth_sim.ros.ros2_control_controllers --robot $$r > config/$${r}_controllers.yaml; \
	  echo "config/$${r}_controllers.yaml"; done

# The physics kernels built with AddressSanitizer and UndefinedBehaviorSanitizer into
# build/sanitize/ (not the package's own module; kernels/build.py --sanitize), then the physics
# tests with that module ($$STARLETH_KERNELS_SANITIZED) and the sanitizers' runtimes preloaded
# (Python is not instrumented: leaks are not checked; an error or undefined behaviour fails).
SANITIZE_DIR := build/sanitize
SANITIZE_TESTS := test_bitexact test_adaptive_alpha test_coordinates test_drives test_hard_contacts \
        test_impedance test_impedance_commands test_kernel_layouts test_kinematics_dynamics \
        test_physics_analytic test_physics_robot test_solvers test_state test_step_down \
        test_terrain test_terrain_walk test_prox_stall test_bilateral_relaxation
# Every C file of the tree in the style of .clang-format (make test checks it)
C_FILES = $(shell git ls-files '*.c' '*.h' 2>/dev/null || find starleth_sim starleth_controller starleth_interface -name '*.[ch]')
format: test-deps
	$(VENV)/bin/clang-format -i $(C_FILES)

# the subset `make test` runs under the sanitizers: every preset's step (bitexact), the
# prepared and profiled steps (state), the solvers, the impedance step, the packed layouts
SANITIZE_QUICK := test_bitexact test_solvers test_kernel_layouts test_state \
        test_impedance_commands test_physics_analytic
sanitize: venv test-deps robots
	@so=$(SANITIZE_DIR)/_kernels$$($(VPY) -c 'import sysconfig; print(sysconfig.get_config_var("EXT_SUFFIX"))'); \
	$(VPY) starleth_sim/physics/kernels/build.py --sanitize $$so || exit 2; \
	cc=$${CC:-cc}; \
	STARLETH_KERNELS_SANITIZED=$$PWD/$$so \
	LD_PRELOAD="$$($$cc -print-file-name=libasan.so) $$($$cc -print-file-name=libubsan.so)" \
	ASAN_OPTIONS=detect_leaks=0:abort_on_error=1 UBSAN_OPTIONS=halt_on_error=1:print_stacktrace=1 \
	$(VPY) -m pytest -q -p no:cacheprovider $(foreach t,$(SANITIZE_TESTS),$(wildcard test/*/$(t).py)) \
	  $(PYTEST_ARGS)

# The compiler's sanitizer runtimes (Debian / Ubuntu: libasan and libubsan of the gcc in use)
sanitizer-libs:
	@v=$$($${CC:-cc} -dumpversion | cut -d. -f1); \
	echo "installing libasan / libubsan for gcc $$v (sudo apt-get)"; \
	sudo apt-get install -y "libgcc-$$v-dev" || sudo apt-get install -y libasan8 libubsan1

clean:
	rm -rf build install log *.egg-info .pytest_cache .ruff_cache
	find . -path ./$(VENV) -prune -o -name __pycache__ -type d -prune -exec rm -rf {} +

distclean: clean
	rm -rf $(VENV)
