# offload workspace. `make test` and `make demo` install what they need first (Debian packages, the
# .venv, the catkin build) and skip what is already done.
SHELL := /bin/bash
.DEFAULT_GOAL := help
.PHONY: help deps venv build test demo demo-options bench-policies bench-fleet-learning bench-planner bench-link bench-flood bench-decision bench-online bench-offline bench-fleet fuzz mutate clean

ROOT := $(CURDIR)
VENV := $(ROOT)/.venv
PY := $(VENV)/bin/python3
NOETIC := /opt/ros/noetic/setup.bash

# Debian's own ROS 1 packages; skipped when ROS Noetic is installed in /opt/ros/noetic.
ROS_DEBS := ros-base-dev python3-rospy python3-roslaunch python3-rostest python3-rosbag python3-rosgraph libnav-msgs-dev \
	python3-nav-msgs catkin ros-message-generation librostest-dev python3-tf2-ros \
	libdiagnostic-updater-dev python3-diagnostic-updater libdiagnostic-aggregator-tools libdiagnostic-aggregator-dev \
	libdynamic-reconfigure-config-init-mutex-dev python3-dynamic-reconfigure \
	librosbag-storage-dev libtopic-tools-dev
BUILD_DEBS := g++ cmake make pybind11-dev libgtest-dev libgmock-dev python3-dev python3-venv libzmq3-dev
# Test and benchmark tools: HAProxy in front of several cloud servers (fleet test, make bench-fleet) and
# systemd-analyze for the unit file check.
TEST_DEBS := haproxy systemd
DEBS := $(BUILD_DEBS) $(TEST_DEBS) $(if $(wildcard $(NOETIC)),,$(ROS_DEBS))

# Every recipe that needs ROS starts with this: Noetic's setup if present, then the devel space.
ROSENV := set -eo pipefail; export ROS_HOME=$(ROOT)/.ros; \
	$(if $(wildcard $(NOETIC)),source $(NOETIC);) \
	if [ -f $(ROOT)/devel/setup.bash ]; then source $(ROOT)/devel/setup.bash; fi;

help:
	@echo "make test           install, build, run gtest + pytest + rostest (fails when any test fails)"
	@echo "make build          install Debian packages, .venv and build the catkin workspace"
	@echo "make bench-planner  planner benchmark against scipy (prints measured figures)"
	@echo "make bench-link     cloud link benchmark against raw pyzmq (prints measured figures)"
	@echo "make bench-flood    one robot's pings while another key sends 64 MiB plans (CONNECTIONS=12)"
	@echo "make bench-decision learner decision latency, p50/p99 per forward path"
	@echo "make bench-fleet    50 robots against 3 cloud servers behind HAProxy, one killed mid-run"
	@echo "make fuzz           coverage-guided fuzzing of the protocol, map loaders and bag reader (FUZZ_SECONDS each)"
	@echo "make demo           the whole system on one machine, ~3 min (STEPS=, MAP=, LINK=wan|edge, UNKNOWN=free,"
	@echo "                    POLICY=, MODE=, HEDGE=1, SEED=, RVIZ=1, FLEET=1 (with POLICY=dqn MODE=deployed),"
	@echo "                    HEADLESS=1: RViz on Xvfb, saved as rviz.png); runs/<time>/"
	@echo "make bench-online   what the learner node adds to a request over calling the planner directly"
	@echo "make bench-policies every routing policy live on the same seeded conditions (SCENARIO=stationary|handover|load-shift|"
	@echo "                    map-switch|drift|file.yaml, MAP=, LINK=, STEPS=, SEED=, POLICIES=, REPEATS=, LEARN_PROBE_RATE=,"
	@echo "                    DEPLOY_MODEL=batch|online)"
	@echo "make bench-fleet-learning robots that differ learning through one fleet learner vs alone (STEPS=, ROBOTS=, ARMS=)"
	@echo "make bench-offline  bag ingest (transitions/s) and offline DQN training (steps/s, batch 64)"
	@echo "make mutate         mutation testing: survival rate of reward/state/dqn/protocol, then C++ core mutants"

deps:
	@missing=$$(for p in $(DEBS); do dpkg-query -W -f='$${Status}\n' $$p 2>/dev/null | grep -q '^install ok installed' || echo $$p; done); \
	if [ -n "$$missing" ]; then \
		echo "installing Debian packages:" $$missing; \
		apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q $$missing; \
	fi

$(VENV)/.installed: requirements.txt | deps
	@[ -x $(PY) ] || /usr/bin/python3 -m venv --system-site-packages $(VENV)
	@touch $(VENV)/CATKIN_IGNORE
	$(PY) -m pip install -q -r requirements.txt
	@# A venv made before pyzmq was built on Debian's libzmq keeps the wheel's slow libsodium: rebuild it.
	@$(PY) src/offload_cloud/src/offload_cloud/curve_speed.py \
		|| $(PY) -m pip install -q --force-reinstall --no-deps --no-binary pyzmq $$(grep '^pyzmq==' requirements.txt)
	@touch $@

venv: $(VENV)/.installed

build: venv
	@# pipefail: a failed catkin_make fails the target; `|| true` only covers grep finding no line to show.
	@$(ROSENV) catkin_make --source . -DPYTHON_EXECUTABLE=$(PY) -DCMAKE_BUILD_TYPE=Release -j2 2>&1 \
		| { grep -Ev '^(make\[|-- |\[ *[0-9]+%\] (Built|Generating|Building)|Scanning|Consolidate)' || true; }
	@# The venv sees the devel space without `source devel/setup.bash`, so the README's offline commands
	@# (`.venv/bin/python -m offload_learner_py.offline.retrain ...`) work in a fresh shell.
	@echo "$(ROOT)/devel/lib/python3/dist-packages" > "$$($(PY) -c 'import sysconfig; print(sysconfig.get_path("purelib"))')/offload_workspace.pth"

# catkin_make run_tests exits 0 when tests fail: catkin_test_results decides.
test: build
	@rm -rf build/test_results
	@$(ROSENV) catkin_make --source . -j2 run_tests > build/run_tests.log 2>&1 || { tail -50 build/run_tests.log; exit 1; }; \
	status=0; $(PY) -m pytest --junitxml=build/test_results/pytest/pytest.xml || status=$$?; \
	$(PY) tools/test_summary.py build/test_results || status=1; \
	exit $$status

bench-planner: build
	@$(ROSENV) $(PY) -m offload_demos.bench_planner

bench-link: build
	@$(ROSENV) $(PY) -m offload_demos.bench_link

CONNECTIONS ?= 12
bench-flood: build
	@$(ROSENV) $(PY) -m offload_demos.bench_flood --connections $(CONNECTIONS)

bench-fleet: build
	@$(ROSENV) $(PY) -m offload_demos.fleet --robots 50 --servers 3 --requests 40 --kill-at-s 1.5 --baseline

# Longer coverage-guided runs than `make test` does; FUZZ_SECONDS per target.
FUZZ_SECONDS ?= 120
fuzz: build
	@mkdir -p build/fuzz && cd build/fuzz && rm -rf offload-fuzz-* && for target in protocol movingai map_yaml map_image; do \
		echo "== $$target ($(FUZZ_SECONDS) s)"; \
		$(ROSENV) $(PY) -m offload_demos.fuzz $$target -max_total_time=$(FUZZ_SECONDS) -max_len=4096 \
			2>&1 | grep -E '^(Done|==[0-9]+== ERROR)|Error' || exit 1; done; \
	echo "== bag reader ($(FUZZ_SECONDS) s)"; \
	$(ROSENV) $(PY) -m offload_demos.fuzz_bag -max_total_time=$(FUZZ_SECONDS) -max_len=65536 \
		-rss_limit_mb=2048 2>&1 | grep -E '^(Done|==[0-9]+== ERROR)|Error'


bench-decision: build
	@$(ROSENV) $(PY) -m offload_demos.bench_decision

STEPS ?= 360
# POLICY, MODE and SEED unset pass nothing: offload_demo.launch's value, else the learner's default.
# Checked before the build and before ROS: a bad STEPS or a MAP that is not a file fails in one line at once
# (the driver then checks the map's YAML and image before it starts anything).
demo-options:
	@case "$(STEPS)" in ''|*[!0-9]*|0) echo "error: STEPS must be a positive integer, got '$(STEPS)'" >&2; exit 2;; esac
	@if [ -n "$(MAP)" ] && [ ! -f "$(MAP)" ]; then echo "error: MAP $(MAP): no such file" >&2; exit 2; fi
	@case "$(LINK)" in ''|wan|edge) ;; *) echo "error: LINK must be wan or edge, got '$(LINK)'" >&2; exit 2;; esac
	@case "$(UNKNOWN)" in ''|free|obstacle) ;; *) echo "error: UNKNOWN must be free or obstacle, got '$(UNKNOWN)'" >&2; exit 2;; esac

demo: demo-options build
	@# RViz only when asked for: it pulls a desktop stack a headless robot or CI does not need. HEADLESS=1
	@# runs it on Xvfb and keeps its last frame as runs/<time>/rviz.png (offload_demos.rviz_view).
	@missing=$$(for p in $(if $(RVIZ)$(HEADLESS),rviz) $(if $(HEADLESS),xvfb); do \
		dpkg-query -W -f='$${Status}\n' $$p 2>/dev/null | grep -q '^install ok installed' || echo $$p; done); \
	if [ -n "$$missing" ]; then apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q $$missing; fi
	@$(ROSENV) $(if $(and $(MAP),$(RVIZ)$(HEADLESS)),mkdir -p .ros; $(PY) -m offload_demos.rviz_view fit --map $(MAP) \
		--out .ros/offload.rviz; export OFFLOAD_RVIZ_CONFIG=$(ROOT)/.ros/offload.rviz;) \
		$(if $(HEADLESS),$(PY) -m offload_demos.rviz_view headless --runs-dir runs --) \
		$(PY) -m offload_demos.driver --launch launch/offload_demo.launch --steps $(STEPS) \
		$(if $(POLICY),--policy $(POLICY)) $(if $(SEED),--seed $(SEED)) $(if $(MODE),--mode $(MODE)) $(if $(MAP),--map $(MAP)) $(if $(RVIZ)$(HEADLESS),--rviz) \
		$(if $(HEDGE),--hedge) $(if $(MODEL),--model $(MODEL)) $(if $(LINK),--link $(LINK)) \
		$(if $(FLEET),--fleet $(if $(SEED_BAG),--fleet-seed-bag $(SEED_BAG))) \
		$(if $(filter free,$(UNKNOWN)),--plan-unknown)

# Every routing policy live, decisions acting, on the demo's seeded conditions or a SCENARIO's (about 2 min a policy
# at STEPS=200, 3 min at the changing scenarios' 400-480, plus a learning run for the DQN and the link-failure run).
bench-policies: build
	@$(ROSENV) $(PY) -m offload_demos.bench_policies $(if $(filter command line environment,$(origin STEPS)),--steps $(STEPS)) $(if $(SEED),--seed $(SEED)) \
		$(if $(MAP),--map $(MAP)) $(if $(POLICIES),--policies $(POLICIES)) $(if $(CHECKPOINT),--checkpoint $(CHECKPOINT)) \
		$(if $(LINK),--link $(LINK)) $(if $(filter free,$(UNKNOWN)),--plan-unknown) $(if $(REPEATS),--repeats $(REPEATS)) \
		$(if $(SCENARIO),--scenario $(SCENARIO)) $(if $(LEARN_PROBE_RATE),--learning-probe-rate $(LEARN_PROBE_RATE)) \
		$(if $(DEPLOY_MODEL),--deploy-model $(DEPLOY_MODEL))

# Robots that differ (map, link, CPU budget) learning through one fleet learner against each learning alone, live,
# one run at a time (STEPS= per run, default 400; ROBOTS=, ARMS=), then a bad model pushed to the fleet.
bench-fleet-learning: build
	@$(ROSENV) $(PY) -m offload_demos.bench_fleet_learning --steps $(if $(filter command line environment,$(origin STEPS)),$(STEPS),400) \
		$(if $(ROBOTS),--robots $(ROBOTS)) $(if $(ARMS),--arms $(ARMS))

bench-online: build
	@$(ROSENV) $(PY) -m offload_demos.bench_online

bench-offline: build
	@$(ROSENV) $(PY) -m offload_demos.bench_offline
# cosmic-ray over the learner's reward, state and DQN modules, the cloud protocol and every module that decides,
# routes, admits or evaluates (about an hour),
# then the hand-written mutants of the Python modules (tools/py_mutants.yaml, about 2 min) and of dijkstra.cpp
# (tools/cpp_mutants.yaml, about 5 min).
mutate: build
	@$(ROSENV) $(PY) tools/mutate_py.py; $(PY) tools/mutate_hand_py.py; $(PY) tools/mutate_cpp.py

clean:
	rm -rf build devel .ros
