# Two commands do everything on a fresh machine: `make demo` and `make test`.
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# Ray RLlib (examples/train_rllib.py and its test) in a venv of its own: ray[rllib] 2.60 pins
# gymnasium 1.2.2, this project runs 1.4. ~2 min to build on a machine with the wheels cached.
RLLIB_VENV ?= .venv-rllib
RLLIB_STAMP := $(RLLIB_VENV)/.installed

.PHONY: demo test docs bench clean ros1 rllib

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

test: $(STAMP) ros1 $(RLLIB_STAMP)
	$(VENV)/bin/ruff check openconvoy tests benchmarks examples docs/hooks
	$(VENV)/bin/ruff format --check openconvoy tests benchmarks examples docs/hooks
	$(VENV)/bin/mypy
	$(MAKE) docs
	$(VENV)/bin/python -m pytest -q

# The documentation site, strict: a broken link, reference or generated table fails.
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --quiet

bench: $(STAMP)
	for b in benchmarks/*.py; do $(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) $(RLLIB_VENV) .pytest_cache build *.egg-info
