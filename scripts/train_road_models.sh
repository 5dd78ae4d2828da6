#!/usr/bin/env bash
# Train the "road" model set (docs/controller.md, docs/density.md): the C3M controller on the road domain,
# its density training data (exact Liouville) and both density predictors, with the package's own commands.
#
#   bash scripts/train_road_models.sh controller   # phase 1: C3M (GPU if present), then the density data
#   bash scripts/train_road_models.sh density      # phase 2: both density networks (in parallel on one GPU)
#   bash scripts/train_road_models.sh all          # both phases
#
# Environment: PY (python, default python3), RES (work directory, default results/road), OUT (where copies of the
# weights and logs go, default $RES/out), DEVICE (cuda or cpu, default: cuda if torch sees one), C3M_EPOCHS,
# C3M_BATCH, DATA_REFS, DENSITY_TIME (seconds per density network), TRAJ_EPOCHS (epochs of the trajectory head; default
# the configuration's 60), THREADS / DENSITY_THREADS. The defaults suit a GPU machine. The shipped road weights were
# made on a 2-core CPU machine (no GPU was available; stop 49): the controller with
#   RES=results/road DEVICE=cpu THREADS=1 C3M_EPOCHS=60 C3M_BATCH=2048 bash scripts/train_road_models.sh controller
# (12 000 steps, 17 min on one idle thread) and the density data and networks with the commands recorded in their
# JSON files and docs/density.md, which are what this script's data phase (32768 references, 2 workers) and
#   RES=results/road DEVICE=cpu DENSITY_TIME=3600 TRAJ_EPOCHS=120 bash scripts/train_road_models.sh density
# run (stop 49: data 5.2 min; trajectory head 16.2 min, pointwise 14.5 min, side by side, one thread each). The
# shipped trajectory head is stop 62's, on four times the references (DATA_REFS=131072 with the fixed-step data of
# `--set liouville.integrator=rk4`: data 11.4-13.9 min with 2 workers; then the head alone, 6 x 256 deep with the
# absolute loss and a lighter log-density weight (`--set layers=6 --set loss=l1 --set log_density_weight=0.3`), 120
# epochs on 2 threads, 45.6 min, with the train command in
# docs/density.md: this script's density phase trains both networks side by side under DENSITY_TIME and would stop
# it early on a 2-core CPU);
# the shipped pointwise net is stop 60's, on 32768 references (this script's data phase with
# --set liouville.integrator=rk4), 20 epochs on 1 thread with --set loss=l1, 7.3 min.
# docs/controller.md and docs/density.md record the exact commands and times.
set -eo pipefail
PHASE=${1:-all}
PY=${PY:-python3}
RES=${RES:-results/road}
OUT=${OUT:-$RES/out}
export PYTHONPATH=$PWD/src${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1
DEVICE=${DEVICE:-$($PY -c 'import torch; print("cuda" if torch.cuda.is_available() else "cpu")')}
W=src/density_planner/weights
DP="$PY -m density_planner"
mkdir -p "$RES" "$OUT"
log() { echo "[$(date -u +%H:%M:%S) +${SECONDS}s] $*" | tee -a "$OUT/train_road.log"; }
log "phase $PHASE on $DEVICE; torch $($PY -c 'import torch; print(torch.__version__)'); $(nproc) cores"
[ "$DEVICE" = cuda ] && nvidia-smi --query-gpu=name,memory.total --format=csv,noheader | tee -a "$OUT/train_road.log"

C3M_SET=(--set domain=road --set min_speed=0.3 --set 'architecture.v_range=[0,40]' --set architecture.speed_feature_scale=2.0)
START_SET=(--set 'start_low=[-10,-10,-3.14159,0.5,0]' --set 'start_high=[10,10,3.14159,38,0]')

if [ "$PHASE" = controller ] || [ "$PHASE" = all ]; then
  C3M_BATCH=${C3M_BATCH:-8192}
  if [ -z "${C3M_EPOCHS:-}" ]; then
    # time one epoch (200 steps) in a scratch directory, then fit the run into C3M_SECONDS of training
    t0=$SECONDS
    $DP train controller --out "$RES/c3m_probe" --no-resume --epochs 1 "${C3M_SET[@]}" --set batch_size=$C3M_BATCH \
      --device "$DEVICE" --check-samples 1000 --check-references 10 --quiet > /dev/null
    probe=$((SECONDS - t0))
    C3M_EPOCHS=$($PY -c "import json; h=json.load(open('$RES/c3m_probe/history.json')); t=h['wall_time'][-1]; \
print(max(10, min(60, int(${C3M_SECONDS:-170} / max(t, 1e-3)))))")
    log "probe: one epoch in $($PY -c "import json; print(round(json.load(open('$RES/c3m_probe/history.json'))['wall_time'][-1], 2))") s (command ${probe} s) -> $C3M_EPOCHS epochs"
  fi
  log "C3M: $C3M_EPOCHS epochs x 200 steps, batch $C3M_BATCH"
  $DP train controller --out "$RES/c3m" --epochs "$C3M_EPOCHS" "${C3M_SET[@]}" --set batch_size=$C3M_BATCH \
    --device "$DEVICE" --threads "${THREADS:-$(nproc)}" --export $W/controller_c3m_road.pt --quiet 2>&1 | tee -a "$OUT/train_road.log"
  cp $W/controller_c3m_road.pt $W/controller_c3m_road.json "$OUT/"
  cp "$RES/c3m/history.json" "$OUT/c3m_history.json"

  DATA_REFS=${DATA_REFS:-32768}
  log "density data: $DATA_REFS references x 8 samples on $DEVICE"
  if [ "$DEVICE" = cuda ]; then
    DATA_DEV=(--set device=cuda --set references_per_shard=${SHARD:-2048} --workers 1)
  else
    DATA_DEV=(--set references_per_shard=${SHARD:-256} --workers "$(nproc)")
  fi
  if ! $DP data density --out "$RES/density_data" --references "$DATA_REFS" --samples 8 --set domain=road \
      "${START_SET[@]}" "${DATA_DEV[@]}" --quiet 2>&1 | tee -a "$OUT/train_road.log"; then
    log "data generation on $DEVICE failed; again with CPU workers"
    $DP data density --out "$RES/density_data" --references "$DATA_REFS" --samples 8 --set domain=road \
      "${START_SET[@]}" --set references_per_shard=${SHARD:-256} --workers "$(nproc)" --quiet 2>&1 | tee -a "$OUT/train_road.log"
  fi
fi

if [ "$PHASE" = density ] || [ "$PHASE" = all ]; then
  DENSITY_TIME=${DENSITY_TIME:-170}
  log "density networks: both in parallel, at most $DENSITY_TIME s of training each"
  $DP train density --arch trajectory --data "$RES/density_data" --out "$RES/train_trajectory" --set device=$DEVICE --threads "${DENSITY_THREADS:-1}" \
    --set layers=6 --set loss=l1 --set log_density_weight=0.3 ${TRAJ_EPOCHS:+--epochs "$TRAJ_EPOCHS"} --time-limit "$DENSITY_TIME" --export $W/density_trajectory_road.pt --quiet > "$OUT/train_trajectory.log" 2>&1 &
  p1=$!
  $DP train density --arch pointwise --data "$RES/density_data" --out "$RES/train_pointwise" --set device=$DEVICE --threads "${DENSITY_THREADS:-1}" \
    --epochs 20 --set batch_size=1024 --set loss=l1 --time-limit "$DENSITY_TIME" --export $W/density_pointwise_road.pt --quiet \
    > "$OUT/train_pointwise.log" 2>&1 &
  p2=$!
  wait $p1 || log "trajectory training failed"
  wait $p2 || log "pointwise training failed"
  tail -n 3 "$OUT/train_trajectory.log" "$OUT/train_pointwise.log" | tee -a "$OUT/train_road.log"
fi
# one archive with everything the package ships for the road set (the device returns at most 8 files)
tar czf "$OUT/road_weights.tar.gz" $W/*_road.pt $W/*_road.json 2>/dev/null || true
log "done"
