# Set-up is idempotent: the venv is created and the project installed only when missing or when
# pyproject.toml changed. MUJOCO_GL=egl renders on the CPU through Mesa's software EGL.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
export MUJOCO_GL ?= egl
export PYOPENGL_PLATFORM ?= egl
EGL_PACKAGES := libegl1 libgl1 libgl1-mesa-dri libegl-mesa0 libglvnd0 libglx-mesa0
# Open3D (the extra peers) loads libusb when imported.
PEER_PACKAGES := libusb-1.0-0

.PHONY: run test test-slow lint bench data weights system-deps setup clean

run: setup
	$(PY) -m sim.run_episode --object phone

# The fast tier: unit tests and fast integration (about 2-3 minutes on 2 cores).
test: setup
	$(PY) -m pytest -q -m "not slow"

# The slow tier: the gate's episodes, Ray clusters, tree copies through lint-imports, soaks.
test-slow: setup
	$(PY) -m pytest -q -m slow

lint: setup
	$(VENV)/bin/ruff check . && $(VENV)/bin/ruff format --check . && $(VENV)/bin/lint-imports
	$(VENV)/bin/vulture sim perception grasping posegrasp bench studies tests/vulture_whitelist.py
	$(VENV)/bin/mypy

# The speed benchmarks against their targets, in short runs (bench/README.md): every bench runs
# even after a miss, and the target fails when any bench missed a target or failed.
BENCHES := "sim_speed.py --seeds 3 --sim-seconds 2 --frames 10" "episode_speed.py --episodes 1" \
	"estimate_latency.py --images 12" "estimate_latency.py --stages --images 6" \
	"evaluate_speed.py --estimator hybrid --episodes 3" "refine_speed.py --images 10" \
	"datagen_speed.py --paper 200 --headcam 40" \
	"trainer_speed.py --nets posenet --batches 64 --seconds 2 --rounds 1"
bench: setup
	@failed=""; for b in $(BENCHES); do echo "== python bench/$$b"; \
	  $(PY) bench/$$b || failed="$$failed bench/$${b%% *}"; done; \
	if [ -n "$$failed" ]; then echo "missed a target or failed:$$failed"; exit 1; fi; \
	echo "every bench met its targets"

# Training data (outside git: $$POSEGRASP_DATA, else data/) and the shipped weights, from scratch.
DATA_COUNTS := paper:train:70000 paper:val:1000 paper:test:1000 \
	headcam:train:160000 headcam:val:500 headcam:test:500
# Head-camera test scenes of the tiers (folders headcam_<tier>), for accuracy per tier.
TIER_COUNTS := hard:train:9000 hard:val:500 hard:test:500 clutter:test:300 any-pose:test:300 \
	any-pose:train:3000 far:train:20000 far:val:300 far:test:300
# Head-camera scenes in rooms drawn for training (`--rooms FAMILY`, folders
# headcam[_<tier>]_rooms[_joint]; `-` is the mixed table scenes), for hybrid-global-rooms.
ROOM_COUNTS := hard:train:2500:wide hard:val:200:wide -:train:2500:wide any-pose:train:1000:wide \
	hard:train:5500:joint hard:val:200:joint -:train:2500:joint
# Head-camera scenes of a bank's meshes alone, in rooms (`--bank BANK --rooms FAMILY`, folders
# headcam_bank[_<bank>]_rooms...), for hybrid-global-unseen's detector of any object; the held-out
# bank's measure it.
BANK_COUNTS := training:train:4000:wide training:val:200:wide shapes:train:3000:wide \
	shapes:val:100:wide held-out:val:300:wide
data: setup
	@for spec in $(DATA_COUNTS); do IFS=: read dist split count <<< "$$spec"; \
	  $(PY) -m perception.training.datagen --dist $$dist --split $$split --count $$count --workers 2 \
	  || exit 1; done
	@for spec in $(TIER_COUNTS); do IFS=: read tier split count <<< "$$spec"; \
	  $(PY) -m perception.training.datagen --dist headcam --tier $$tier --split $$split \
	  --count $$count --workers 2 || exit 1; done
	@for spec in $(ROOM_COUNTS); do IFS=: read tier split count family <<< "$$spec"; \
	  if [ "$$tier" = "-" ]; then tier_arg=""; else tier_arg="--tier $$tier"; fi; \
	  $(PY) -m perception.training.datagen --dist headcam $$tier_arg --rooms $$family \
	  --split $$split --count $$count --workers 2 || exit 1; done
	@for spec in $(BANK_COUNTS); do IFS=: read bank split count family <<< "$$spec"; \
	  $(PY) -m perception.training.datagen --dist headcam --bank $$bank --rooms $$family \
	  --split $$split --count $$count --workers 2 || exit 1; done

# The shipped weights, from scratch: every stage of the recipe (perception/training/recipe.py,
# `python -m perception.training.recipe --dry-run` prints it) that is not done yet, each resuming
# its checkpoint under $$POSEGRASP_DATA/checkpoints/<stage>; then one step ships them into
# perception/weights/ (copied, hashed, their manifests recorded), draws the pose nets' curves and
# records the test figures of the weights shipped.
weights: data
	$(PY) -m perception.training.recipe
	$(PY) -m perception.training.recipe --ship --plot docs/training_curves.png
	$(PY) -m perception.training.tables --weights perception/weights/posenet_ours.pt --record
	$(PY) -m perception.training.tables --weights perception/weights/posenet_paper.pt --record
	$(PY) -m perception.training.tables --boxes detector --record
	$(PY) -m perception.training.tables --weights perception/weights/posenet_paper.pt \
	  --dists paper,headcam --boxes detector --detector perception/weights/paper_protocol/detector.pt \
	  --json docs/table2_paper_detections.json

setup: system-deps $(STAMP)

# Software EGL needs Mesa, Open3D libusb; install them with apt-get when missing and we are root.
system-deps:
	@missing=""; for p in $(EGL_PACKAGES) $(PEER_PACKAGES); do \
	  dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
	    echo "installing system packages:$$missing"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing; \
	  else echo "missing system packages:$$missing (install them with apt-get as root)"; fi; \
	fi

# opencv-contrib-python-headless replaced opencv-python-headless: both own cv2/, so a venv that
# has the plain build drops both and gets the contrib build afresh.
$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	@if $(PY) -m pip show -q opencv-python-headless >/dev/null 2>&1; then \
	  $(PY) -m pip uninstall -q -y opencv-python-headless opencv-contrib-python-headless; fi
	$(PY) -m pip install -q -e ".[dev,ray,peers,shifts]"
	$(PY) -m pip install -q --no-deps -e examples/crude-estimator
	@touch $(STAMP)

clean:
	rm -rf $(VENV) *.egg-info
