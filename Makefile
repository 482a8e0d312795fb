# texspace: two commands on a fresh Debian / Python 3.11 machine.
#   make run    virtual environment, runtime + train extra (torch==2.13.0, CPU: fits refine
#               every upload), migrate, API + worker on SQLite at http://127.0.0.1:$(TEXSPACE_PORT)
#               (default 8000)
#   make test   test + train extras (torch==2.13.0, CPU), then pytest
#   make test-fast   the same without the e2e, scaleout, browser and slow tests (the edit loop)
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(VENV)/bin/pip
TEXSPACE_PORT ?= 8000
TEXSPACE_DATA_DIR ?= data
export TEXSPACE_PORT TEXSPACE_DATA_DIR
PYTEST_ARGS ?=

.PHONY: run test test-fast install install-test migrate serve bench readme-figure grain-figure triplanar-figure clean-data

$(PY):
	$(PYTHON) -m venv $(VENV)

# stamps: re-install only when pyproject.toml changes, so `make run` restarts quickly
$(VENV)/.installed-run: pyproject.toml | $(PY)
	$(PIP) install --disable-pip-version-check --no-compile -q -e '.[train]'
	touch $@

$(VENV)/.installed-test: pyproject.toml | $(PY)
	$(PIP) install --disable-pip-version-check -q -e '.[train,test]'
	touch $@ $(VENV)/.installed-run

install: $(VENV)/.installed-run
install-test: $(VENV)/.installed-test

migrate: install
	$(VENV)/bin/texspace migrate

# serve applies the migrations itself before starting the API and the worker
run: install
	$(VENV)/bin/texspace serve --host 127.0.0.1 --port $(TEXSPACE_PORT)

test: install-test
	$(PY) -m pytest $(PYTEST_ARGS)

test-fast: install-test
	$(PY) -m pytest -m "not e2e and not scaleout and not browser and not slow" $(PYTEST_ARGS)

bench: install-test
	$(PY) bench/run.py
	$(PY) bench/load.py   # 32 clients, 60 s, on a real `texspace serve` (loopback)

# four photos uploaded at once to a fresh `texspace serve`: each one's first refined tiles
# and final sampler, in seconds from its upload (one upload alone first, the reference)
.PHONY: bench-refine
bench-refine: data
	$(PY) bench/refinement_queue.py $(BENCH_REFINE_ARGS)

# the style error a fit reaches in 30, 60 and 120 s (bf16 where native) against a 240-s
# float32 fit and the encoder code, on three validation photos (~25 minutes)
.PHONY: bench-fit-budget
bench-fit-budget: data
	$(PY) bench/fit_budget.py $(BENCH_FIT_BUDGET_ARGS)

# the README picture: exemplars beside tiles synthesised from their codes; the shipped one
# adds each photo's fit: make fits FIT_ARGS='--threads 1' FIT_JOBS=2 and FIGURE_ARGS='--fits runs/fits'
readme-figure: data
	$(PY) -m eval.readme_figure docs/images/exemplar-and-tile.png $(FIGURE_ARGS)

# the model card's wood picture: a default-length grain fit on the three axis planes
grain-figure: data
	$(PY) -m model.fit data/textures/val/miniworld_wood_1.png runs/fits-grain/miniworld_wood_1 --grain y
	$(PY) -m eval.grain_figure

triplanar-figure: data
	$(PY) -m model.fit data/textures/val/miniworld_brick_wall_1.png runs/fits/miniworld_brick_wall_1 --minutes 1 --threads 1
	$(PY) -m eval.triplanar_figure

clean-data:
	rm -rf $(TEXSPACE_DATA_DIR)

# --- the model (torch, the train extra) --------------------------------------------
# make train resumes runs/space, stops after TRAIN_STEPS steps in total, then exports to
# model/weights/. An empty runs/space is seeded from TRAIN_INIT when one is given, a training
# checkpoint of the same photos resumed as it is. Without one the run starts from
# TRAIN_WEIGHTS, the shipped weights by default (--init: Adam starts afresh, the code table at
# the encoder's codes of the photos); TRAIN_WEIGHTS= (empty) trains a space from scratch. (The
# shipped space's own run, make shipped-checkpoint, was trained on a GPU pack's 369 photos,
# not data/textures: make gpu-finetune-pack.)
TRAIN_STEPS ?= 20000
TRAIN_INIT ?=
TRAIN_WEIGHTS ?= model/weights/space.pt
TRAIN_ARGS ?= --patch 64 --batch 4 --lr 2e-4 --warmup 200 --no-nearest --smooth --colour-normalise --isotropic-transforms --threads 2 --ckpt-every 100
.PHONY: data data-large train export evaluate quality-large fits-large

data: install-test
	$(PY) -m model.data fetch

# The opt-in large corpus (docs/DATA.md): ~2.2 GB of Debian packages fetched once into
# the cache, photos into data/textures-large/{train,val}. Needs apt-get and dpkg-deb.
data-large: install-test
	$(PY) -m model.corpus fetch

train: data
	@if [ ! -f runs/space/checkpoint.pt ] && [ -f "$(TRAIN_INIT)" ]; then \
		mkdir -p runs/space && cp "$(TRAIN_INIT)" runs/space/checkpoint.pt; fi
	$(PY) -m model.train --out runs/space $(if $(TRAIN_WEIGHTS),--init $(TRAIN_WEIGHTS)) --steps $(TRAIN_STEPS) $(TRAIN_ARGS)
	$(PY) -m model.export runs/space/checkpoint.pt model/weights

export: install-test
	$(PY) -m model.export runs/space/checkpoint.pt model/weights

# The shipped space's full training checkpoint (16 MiB with its Adam state) is not in the
# tree (docs/ARCHITECTURE.md, "What git holds"): this writes it from the last commit that
# had it, where the history is at hand.
SHIPPED_CHECKPOINT := runs/space-train.pt
.PHONY: shipped-checkpoint
shipped-checkpoint: $(SHIPPED_CHECKPOINT)
$(SHIPPED_CHECKPOINT):
	mkdir -p $(dir $@)
	git show "$$(git rev-list -n 1 HEAD -- model/checkpoints/space-train.pt)^:model/checkpoints/space-train.pt" > $@.tmp
	mv $@.tmp $@

# make train-gpu: the same space on a CUDA GPU, in bounded calls. Each call resumes
# runs/space-gpu for GPU_MINUTES of steps (default 9, so that one call with its start and
# export fits a 10-minute command limit; call again to go on), then exports to GPU_EXPORT
# (runs/space-gpu/weights; GPU_EXPORT=model/weights ships it). An empty runs/space-gpu starts
# from GPU_INIT (--init: its weights; its code table where it has the same photos, else the
# encoder's codes of them), the shipped weights by default.
# It installs nothing: the install targets keep torch CPU-only, so PY must be a Python whose
# torch sees CUDA, with data/textures (make data) and the VGG16 cache (python -m model.vgg
# fetch, TEXSPACE_CACHE_DIR) already in place.
GPU_INIT ?= model/weights/space.pt
GPU_MINUTES ?= 9
GPU_STEPS ?= 100000
GPU_EXPORT ?= runs/space-gpu/weights
GPU_ARGS ?= --batch 16 --patch 256 --lr 2e-4 --warmup 100 --no-nearest --smooth --colour-normalise --isotropic-transforms --ckpt-every 500 --quiet
.PHONY: train-gpu
train-gpu:
	$(PY) -m model.train --out runs/space-gpu $(if $(wildcard runs/space-gpu/checkpoint.pt),,--init $(GPU_INIT)) --device cuda --steps $(GPU_STEPS) --minutes $(GPU_MINUTES) $(GPU_ARGS)
	$(PY) -m model.export runs/space-gpu/checkpoint.pt $(GPU_EXPORT)

# make gpu-pack: for a lent GPU machine that takes 64 MiB of files and has no network (the
# device tool): writes gpu/ (ignored by git, ~12 MiB: int8 VGG16 (xz), the training and validation
# photos at the working resolution, eval/gpu_pack.py). GPU_CORPUS=large packs the large
# corpus (docs/DATA.md, "Training on a lent GPU": a JPEG subset bounded to fit, and the recipe
# gpu-large-* below); GPU_LICENCES=non-gpl leaves GPL art out. A fit there: python3 gpu/gpu_pack.py
# fit gpu/val/PHOTO.png $$OUT/fit -- --device cuda --minutes 4. Carry gpu/ there and run, in one call:
#   mkdir -p $$OUT/run && cp runs/space-train.pt $$OUT/run/checkpoint.pt &&
#   python3 gpu/gpu_pack.py train runs/space-train.pt -- --out $$OUT/run \
#     --device cuda --minutes 7.5 GPU_ARGS...
# carrying runs/space-train.pt too (make shipped-checkpoint; the copy makes it resume with its
# Adam state); bring back $$OUT/run/checkpoint.pt, put it at runs/space-train.pt and export here. How the shipped space was made:
# the model card's "The shipped space".
GPU_CORPUS ?= default
GPU_LICENCES ?= all
# large: 256 px short side, long side cropped to 384, JPEG 90, 4 MiB of photos (147 train photos
# of 147 families, 8 val): tree ~33 + pack 11.4 + slim checkpoint 2.7 MiB stay under 64.
# A run resumes only on the pack it started with: keep these the same for all its calls.
GPU_PACK_ARGS ?= $(if $(filter large,$(GPU_CORPUS)),--quality 90 --max-long 384 --photo-mib 4 --val 8)
.PHONY: gpu-pack
gpu-pack: $(if $(filter large,$(GPU_CORPUS)),install-test,data)
	@test -f $(if $(filter large,$(GPU_CORPUS)),data/textures-large,data/textures)/index.json || \
		{ echo "no corpus: make $(if $(filter large,$(GPU_CORPUS)),data-large,data) first"; exit 1; }
	rm -rf gpu
	$(PY) -m eval.gpu_pack pack gpu --corpus $(GPU_CORPUS) --licences "$(GPU_LICENCES)" $(GPU_PACK_ARGS)

# A new space on the large corpus, trained from scratch on a lent GPU in calls of the device
# tool (docs/DATA.md, "Training on a lent GPU"). make gpu-large-command prints the call: carry
# gpu and (after the first call) runs/space-gpu-large/checkpoint.pt; it trains GPU_LARGE_MINUTES
# and puts a slim checkpoint and the call's log in $$OUT/run. Then make gpu-large-back
# FROM=<files_at>/run puts them in runs/space-gpu-large; the next call resumes there.
GPU_LARGE_MINUTES ?= 8
GPU_LARGE_ARGS ?= --code-size 16 --batch 16 --patch 256 --lr 2e-4 --warmup 200 --no-nearest --smooth --colour-normalise --isotropic-transforms --ckpt-every 500 --quiet
.PHONY: gpu-large-command gpu-large-back gpu-large-export
gpu-large-command:
	@echo "carry: [\"gpu\"$$(test -f runs/space-gpu-large/checkpoint.pt && echo ', \"runs/space-gpu-large/checkpoint.pt\"')]   timeout_s: 570"
	@echo 'mkdir -p runs/space-gpu-large $$OUT/run && PYTHONUNBUFFERED=1 python3 gpu/gpu_pack.py train -- --out runs/space-gpu-large --device cuda --minutes $(GPU_LARGE_MINUTES) $(GPU_LARGE_ARGS); python3 gpu/gpu_pack.py slim runs/space-gpu-large/checkpoint.pt $$OUT/run/checkpoint.pt; cp runs/space-gpu-large/log.jsonl $$OUT/run/'
gpu-large-back:
	@test -f "$(FROM)/checkpoint.pt" || { echo "FROM=<files_at>/run: the call's checkpoint.pt and log.jsonl"; exit 1; }
	mkdir -p runs/space-gpu-large
	cp "$(FROM)/checkpoint.pt" runs/space-gpu-large/checkpoint.pt
	cat "$(FROM)/log.jsonl" >> runs/space-gpu-large/log-all.jsonl
gpu-large-export: install-test
	$(PY) -m model.export runs/space-gpu-large/checkpoint.pt runs/space-gpu-large/weights

# The shipped space fine-tuned on a lent GPU, in one call (docs/DATA.md, "Fine-tuning the
# shipped space"): the large corpus's non-GPL training photos (10 MiB of them) + the default
# training photos, starting from the shipped checkpoint; the default validation photos are
# fitted on the GPU beside it. gpu-finetune-pack, then the device call it prints, then
# make gpu-finetune-back FROM=<files_at>: runs/space-large-ft/{checkpoint.pt,log.jsonl,weights},
# runs/fits-gpu/<photo>.
GPU_FINETUNE_PACK_ARGS ?= --quality 90 --max-long 384 --photo-mib 10 --val 8 --add-default
.PHONY: gpu-finetune-pack gpu-finetune-back
gpu-finetune-pack: install-test $(SHIPPED_CHECKPOINT)
	@test -f data/textures-large/index.json -a -f data/textures/index.json || { echo "make data data-large first"; exit 1; }
	rm -rf gpu
	$(PY) -m eval.gpu_pack pack gpu --corpus large --licences non-gpl $(GPU_FINETUNE_PACK_ARGS)
	$(PY) eval/gpu_pack.py slim $(SHIPPED_CHECKPOINT) gpu/init.pt
	cp eval/gpu_finetune.sh gpu/
	@echo 'device run: carry ["gpu"], timeout_s 590, command: bash gpu/gpu_finetune.sh 7 0.33 cuda'
gpu-finetune-back:
	@test -f "$(FROM)/run/checkpoint.pt" || { echo "FROM=<files_at>: the call's run/ and fits.tar"; exit 1; }
	mkdir -p runs/space-large-ft runs/fits-gpu
	cp "$(FROM)/run/checkpoint.pt" "$(FROM)/run/log.jsonl" runs/space-large-ft/
	tar xf "$(FROM)/fits.tar" -C runs/fits-gpu
	$(PY) -m model.export runs/space-large-ft/checkpoint.pt runs/space-large-ft/weights

# The comparison: every variant trained as a space from scratch with the same settings and
# the same number of steps (runs/compare/<variant>), then evaluated on the validation
# exemplars together with the shipped space. One thread per run: `make -j2 compare` runs two at once
# (about 30 minutes per run on an idle 2-core machine). 3,000 steps, not 1,000: at 1,000 the
# learned transforms had not paid off yet and oursNoT scored above ours on every plane seed
# tried (see the model card).
COMPARE_STEPS ?= 3000
COMPARE_ARGS ?= --patch 64 --batch 4 --lr 5e-4 --warmup 200 --no-nearest --smooth --threads 1 --ckpt-every 100 --quiet
VARIANT_NAMES := perlin perlinT mlp oursP oursNoT ours
.PHONY: compare $(addprefix compare-,$(VARIANT_NAMES))
compare: $(addprefix compare-,$(VARIANT_NAMES))
$(addprefix compare-,$(VARIANT_NAMES)): compare-%: data
	$(PY) -m model.train --variant $* --out runs/compare/$* --steps $(COMPARE_STEPS) $(COMPARE_ARGS)

# Single-exemplar fits of every validation exemplar at the default settings
# (runs/fits/<name>), FIT_JOBS at a time, then each fit against the shipped space's
# encoder code. A timed fit's result depends on the steps it gets: the model card's
# figures ran FIT_ARGS='--threads 1' FIT_JOBS=2 on 2 cores (4 minutes, as the service's).
# No detail stage: these measure the working size, as an upload's refinement serves it.
# Each starts from the code its upload stores (texspace encode), as the service's fits do.
FIT_ARGS ?=
FIT_JOBS ?= 1
VAL_IMAGES = $(wildcard data/textures/val/*.png)
UPLOAD_CODE = $$($(VENV)/bin/texspace encode {} | $(PY) -c "import json, sys; print(*json.load(sys.stdin)[\"code\"])")
.PHONY: fits evaluate-fits
fits: data
	printf '%s\n' $(VAL_IMAGES) | xargs -P $(FIT_JOBS) -I {} \
		sh -c '$(PY) -m model.fit {} runs/fits/$$(basename {} .png) --detail-seconds 0 --start-code $(UPLOAD_CODE) $(FIT_ARGS)'

evaluate-fits: data
	$(PY) -m model.evaluate --checkpoint model/weights/space.pt --checkpoint-dir runs/fits \
		--exemplars data/textures/val --out docs/eval/fits

# Noise input and loss, measured: single-exemplar runs from scratch, the same steps for each
# setting, on three validation photos (two structured, one stochastic).
ABLATION_IMAGES ?= miniworld_brick_wall_1 miniworld_floor_tiles_white vpython_gravel
ABLATION_ARGS ?= --mode single --steps 300 --patch 64 --batch 2 --lr 1e-3 --warmup 20 --threads 1 --quiet
ABLATION_SETTINGS := nearest:  linear:--no-nearest  smooth:--no-nearest,--smooth  smooth-swd:--no-nearest,--smooth,--loss,swd
.PHONY: ablation
ablation: data
	for setting in $(ABLATION_SETTINGS); do \
		name=$${setting%%:*}; flags=$$(echo $${setting#*:} | tr , ' '); \
		for image in $(ABLATION_IMAGES); do \
			$(PY) -m model.train $(ABLATION_ARGS) $$flags --exemplar data/textures/val/$$image.png \
				--out runs/ablation/$$name/$$image || exit 1; done; done
	$(PY) -m model.evaluate $(foreach s,$(ABLATION_SETTINGS),--group $(firstword $(subst :, ,$(s)))=runs/ablation/$(firstword $(subst :, ,$(s)))) \
		--exemplars data/textures/val --out docs/eval/ablation

evaluate: data
	$(PY) -m model.evaluate --checkpoint-dir runs/compare --group ours-shipped=model/weights \
		--exemplars data/textures/val --out docs/eval/compare

# What model/structure/ finds (grain, lattices, stripes, boards) on the packaged photos and
# on crops, turns and close-ups cut from them: the reference to diff after a detector change.
.PHONY: structure
structure: data
	$(PY) -m eval.structure --data data/textures --out docs/eval/structure

# Product-level quality: colour (CIELAB), style against colour-matched value
# noise, diversity and oblique / axis slices, all through encoder.onnx + sampler.onnx as
# the service serves them; style over each photo's own floor (eval/style_floor.py)
# for the tiles, by-example noise (eval/by_example.py) and value noise, with medians.
# Another export side by side: QUALITY_ARGS='--model-dir DIR --label NAME'; fits: '--fits runs/fits';
# a model's rows kept as measured before (the GPU fits, when the upload's code changes): '--carry shipped-fit'.
QUALITY_ARGS ?=
.PHONY: quality tune-by-example
quality: data
	$(PY) -m eval.quality --model-dir model/weights --label shipped $(QUALITY_ARGS) \
		--exemplars data/textures/val --out docs/eval/quality

# The same on photos of the large corpus (make data-large) never trained on: one from each of
# QUALITY_FAMILIES validation families (eval/quality.py --families). fits-large fits the same
# photos into runs/fits-large; then QUALITY_ARGS='--fits runs/fits-large' measures them too.
QUALITY_FAMILIES ?= 40
LARGE_VAL = data/textures-large/val
quality-large: install-test
	$(PY) -m eval.quality --model-dir model/weights --label shipped $(QUALITY_ARGS) \
		--exemplars $(LARGE_VAL) --families $(QUALITY_FAMILIES) --out docs/eval/quality-large

fits-large: install-test
	$(PY) -m eval.quality --model-dir model/weights --exemplars $(LARGE_VAL) --families $(QUALITY_FAMILIES) \
		--list | xargs -P $(FIT_JOBS) -I {} sh -c '$(PY) -m model.fit {} runs/fits-large/$$(basename {} .png) --detail-seconds 0 --start-code $(UPLOAD_CODE) $(FIT_ARGS)'

# How far the space reaches (eval/space_reach.py): the best code it has for each of those
# photos (a code-only fit: the space frozen, no structure, REACH_STEPS) beside its encoder's
# code, into docs/eval/space-reach; the codes are kept in runs/space-reach (a rerun only measures).
REACH_STEPS ?= 200
.PHONY: space-reach
space-reach: install-test
	$(PY) -m eval.space_reach --model-dir model/weights --exemplars $(LARGE_VAL) --families $(QUALITY_FAMILIES) \
		--steps $(REACH_STEPS) --codes runs/space-reach --out docs/eval/space-reach $(REACH_ARGS)

# A photo's own resolution (eval/detail.py): the validation photos of 512 px and up fitted with
# their detail stage into runs/fits-detail (kept: a rerun only measures), their tiles scored at the
# photo's own scale with and without it. DETAIL_ARGS='--machine "..."' names the machine in the report.
DETAIL_ARGS ?=
.PHONY: quality-detail
quality-detail: data
	$(PY) -m eval.detail --exemplars data/textures/val --fits runs/fits-detail --out docs/eval/detail $(DETAIL_ARGS)

# The by-example baseline's triangle edge: its style error over the floor per edge, per photo
tune-by-example: data
	$(PY) -m eval.tune_by_example --exemplars data/textures/val --out docs/eval/quality/by_example_tuning.md
