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
	$(VENV)/bin/vulture sim perception grasping posegrasp bench tests/vulture_whitelist.py

bench: setup
	$(PY) bench/sim_speed.py

# Training data (outside git: $$POSEGRASP_DATA, else data/) and the shipped weights, from scratch.
DATA_COUNTS := paper:train:70000 paper:val:1000 paper:test:1000 \
	headcam:train:160000 headcam:val:500 headcam:test:500
# Head-camera test scenes of the tiers (folders headcam_<tier>), for accuracy per tier.
TIER_COUNTS := hard:train:9000 hard:val:500 hard:test:500 clutter:test:300 any-pose:test:300 \
	any-pose:train:3000 far:train:20000 far:val:300 far:test:300
data: setup
	@for spec in $(DATA_COUNTS); do IFS=: read dist split count <<< "$$spec"; \
	  $(PY) -m perception.training.datagen --dist $$dist --split $$split --count $$count --workers 2 \
	  || exit 1; done
	@for spec in $(TIER_COUNTS); do IFS=: read tier split count <<< "$$spec"; \
	  $(PY) -m perception.training.datagen --dist headcam --tier $$tier --split $$split \
	  --count $$count --workers 2 || exit 1; done

# The shipped weights were trained with exactly these commands, in this order (each `--init`
# names the stage it starts from); perception/weights/manifest.json records each stage's command,
# data seeds, validation figures and, where measured, wall time, and docs/DESIGN.md §7
# ("Training") says what the stages are for.
CKPT := $${POSEGRASP_DATA:-data}/checkpoints
weights: data
	$(PY) -m perception.training.train_posenet --variant ours --epochs 16 --limit headcam=5000,paper=20000 \
	  --name posenet_ours_mixed
	$(PY) -m perception.training.train_posenet --variant ours --epochs 14 --dists headcam \
	  --limit headcam=10000 --lr 0.001 --init posenet_ours_mixed --name posenet_ours_head
	$(PY) -m perception.training.train_posenet --variant ours --epochs 6 --dists headcam \
	  --limit headcam=20000 --lr 0.0005 --init posenet_ours_head --name posenet_ours_ft20k
	$(PY) -m perception.training.train_posenet --variant ours --epochs 5 --dists headcam \
	  --limit headcam=40000 --lr 0.0005 --init posenet_ours_ft20k --name posenet_ours_ft40k
	$(PY) -m perception.training.train_posenet --variant ours --epochs 3 --dists headcam,headcam_far \
	  --limit headcam=40000,headcam_far=5000 --lr 0.0002 --init posenet_ours_ft40k \
	  --name posenet_ours_far
	$(PY) -m perception.training.train_posenet --variant ours --epochs 3 --dists headcam,headcam_far \
	  --limit headcam=80000,headcam_far=5000 --lr 0.0003 --init posenet_ours_far \
	  --name posenet_ours_ft80k
	$(PY) -m perception.training.train_posenet --variant ours --epochs 2 --dists headcam,headcam_far \
	  --limit headcam=120000,headcam_far=10000 --lr 0.0003 --init posenet_ours_ft80k \
	  --name posenet_ours_ft120k
	$(PY) -m perception.training.train_posenet --variant ours --epochs 2 --dists headcam,headcam_far \
	  --lr 0.0003 --init posenet_ours_ft120k
	$(PY) -m perception.training.train_posenet --variant ours --dists headcam,headcam_hard \
	  --limit headcam=5000,headcam_hard=3000 --epochs 5 --lr 0.0005 --init posenet_ours_head --name posenet_ours_hard
	$(PY) -m perception.training.train_posenet --variant paper --dists paper --epochs 10 --batch 64 \
	  --limit paper=40000 --precision bf16 --name posenet_paper_bf16
	$(PY) -m perception.training.train_posenet --variant paper --dists paper --epochs 25 --batch 64 \
	  --limit paper=40000 --precision bf16 --channels-last --threads 2 --lr 0.001 \
	  --init posenet_paper_bf16 --name posenet_paper_s2
	$(PY) -m perception.training.train_posenet --variant paper --dists paper --epochs 25 --batch 64 \
	  --limit paper=40000 --precision bf16 --channels-last --threads 2 --lr 0.001 \
	  --init posenet_paper_s2
	$(PY) -m perception.training.export --plot docs/training_curves.png
	$(PY) -m perception.training.train_detector --epochs 8 --out $(CKPT)/detector_base
	$(PY) -m perception.training.train_detector --also headcam_hard --limit 2500 --epochs 1 \
	  --lr 0.0005 --init $(CKPT)/detector_base/detector.pt --export
	$(PY) -m perception.training.train_detector --also paper --limit 2500 --epochs 1 --lr 0.0005 \
	  --init perception/weights/detector.pt --out $(CKPT)/detector_paper --export \
	  --weights-out perception/weights/paper_protocol
	$(PY) -m perception.training.train_detector --data $${POSEGRASP_DATA:-data}/paper --limit 10000 \
	  --epochs 1 --lr 0.0003 --precision bf16 --channels-last \
	  --init perception/weights/paper_protocol/detector.pt --out $(CKPT)/detector_paper2 --export \
	  --weights-out perception/weights/paper_protocol
	$(PY) -m perception.training.train_detector --data $${POSEGRASP_DATA:-data}/headcam_hard \
	  --also headcam_any-pose,headcam --limit 3000 --epochs 3 --lr 0.0005 --precision bf16 \
	  --channels-last --init perception/weights/detector.pt --out $(CKPT)/detector_tiers --export \
	  --weights-out perception/weights/tiers
	$(PY) -m perception.training.train_detector --data $${POSEGRASP_DATA:-data}/headcam_hard \
	  --also headcam_any-pose,headcam --limit 9000 --epochs 1 --lr 0.0003 --precision bf16 \
	  --channels-last --init perception/weights/tiers/detector.pt --out $(CKPT)/detector_tiers2 \
	  --export --weights-out perception/weights/tiers
	$(PY) -m perception.training.train_masknet --epochs 5 --channels-last --out $(CKPT)/masknet \
	  --export
	$(PY) -m perception.training.train_masknet --init perception/weights/tiers/masknet.pt --seed 1 \
	  --epochs 3 --lr 0.001 --channels-last --out $(CKPT)/masknet_ft --export
	$(PY) -m perception.training.train_masknet --protocol paper --epochs 6 --channels-last \
	  --out $(CKPT)/masknet_paper --export
	$(PY) -m perception.training.train_masknet --protocol paper \
	  --init perception/weights/paper_protocol/masknet.pt --seed 1 --epochs 4 --lr 0.001 \
	  --channels-last --out $(CKPT)/masknet_paper_ft --export
	$(PY) -m perception.training.train_masknet --protocol paper \
	  --init perception/weights/paper_protocol/masknet.pt --seed 2 --epochs 4 --lr 0.0005 \
	  --channels-last --out $(CKPT)/masknet_paper_ft2 --export
	$(PY) -m perception.training.train_masknet --protocol paper \
	  --init perception/weights/paper_protocol/masknet.pt --seed 3 --epochs 3 --lr 0.0005 \
	  --detected 10000 --channels-last --out $(CKPT)/masknet_paper_det --export
	$(PY) -m perception.training.train_masknet --protocol paper \
	  --init perception/weights/paper_protocol/masknet.pt --seed 4 --epochs 2 --lr 0.0005 \
	  --detected 20000 --channels-last --out $(CKPT)/masknet_paper_det2 --export
	$(PY) -m perception.training.train_masknet --protocol paper \
	  --init perception/weights/paper_protocol/masknet.pt --seed 5 --epochs 2 --lr 0.0005 \
	  --detected 40000 --channels-last --out $(CKPT)/masknet_paper_det3 --export --expert faucet
	$(PY) -m perception.training.tables --weights perception/weights/posenet_ours.pt --record
	$(PY) -m perception.training.tables --weights perception/weights/posenet_paper.pt --record
	$(PY) -m perception.training.tables --boxes detector --record
	$(PY) -m perception.training.tables --weights perception/weights/posenet_paper.pt \
	  --dists paper,headcam --boxes detector --detector perception/weights/paper_protocol/detector.pt \
	  --json docs/table2_paper_detections.json

setup: system-deps $(STAMP)

# Software EGL needs Mesa; install it with apt-get when it is missing and we are root.
system-deps:
	@missing=""; for p in $(EGL_PACKAGES); do \
	  dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
	    echo "installing system packages:$$missing"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing; \
	  else echo "missing system packages:$$missing (install them with apt-get as root)"; fi; \
	fi

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[dev,ray]"
	@touch $(STAMP)

clean:
	rm -rf $(VENV) *.egg-info
