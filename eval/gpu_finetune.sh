#!/bin/bash
# One call on a lent GPU machine (make gpu-finetune-pack puts this in gpu/): the shipped space
# fine-tuned on the pack's photos (the large corpus's non-GPL training photos + the default
# ones), and fits of the default validation photos timed on the GPU beside it.
#   bash gpu/gpu_finetune.sh [TRAIN_MINUTES=7] [FIT_MINUTES=0.33] [DEVICE=cuda]
# Writes to $OUT: run/checkpoint.pt (slim), run/log.jsonl, run/train.txt, fits.tar (each fit's
# sampler.onnx, code.json, manifest.json), fits.txt and fit-clean.txt (a first fit alone on the
# device: its steps/s), info.txt (the GPU, its use while training). Back here: make gpu-finetune-back.
export PYTHONUNBUFFERED=1 TIMEFORMAT="wall %R s"
TRAIN_MIN=${1:-7}; FIT_MIN=${2:-0.33}; DEV=${3:-cuda}; OUT=${OUT:-/tmp/out}
mkdir -p "$OUT/run" /tmp/fits runs
(nvidia-smi --query-gpu=name,memory.used,utilization.gpu --format=csv 2>&1 | head -3) > "$OUT/info.txt"
python3 -c "import torch; print(torch.__version__, torch.cuda.is_available())" >> "$OUT/info.txt" 2>&1
# 1. one fit alone on the device: a clean steps/s figure
{ time python3 gpu/gpu_pack.py fit gpu/fitval/vpython_gravel.png /tmp/fits/clean -- --device "$DEV" \
  --minutes "$FIT_MIN"; } > "$OUT/fit-clean.txt" 2>&1
# 2. the space: the shipped weights fine-tuned on the pack's photos (codes start at the encoder's)
python3 gpu/gpu_pack.py train gpu/init.pt -- --out runs/large --device "$DEV" --minutes "$TRAIN_MIN" \
  --batch 32 --patch 256 --lr 2e-4 --warmup 100 --decay-by-time --no-nearest --smooth --colour-normalise \
  --isotropic-transforms --ckpt-every 250 --quiet > "$OUT/run/train.txt" 2>&1 &
train=$!
(sleep 150; nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv >> "$OUT/info.txt" 2>&1) &
# 3. the default validation photos fitted beside the training run
for photo in gpu/fitval/*.png; do
  name=$(basename "$photo" .png)
  echo "== $name"; time python3 gpu/gpu_pack.py fit "$photo" "/tmp/fits/$name" -- --device "$DEV" --minutes "$FIT_MIN"
done > "$OUT/fits.txt" 2>&1
wait $train
python3 gpu/gpu_pack.py slim runs/large/checkpoint.pt "$OUT/run/checkpoint.pt" >> "$OUT/run/train.txt" 2>&1
cp runs/large/log.jsonl "$OUT/run/"
(cd /tmp/fits && tar cf "$OUT/fits.tar" --exclude=fit.pt --exclude='sampler_tileable.onnx' .)
ls -la "$OUT" "$OUT/run"
