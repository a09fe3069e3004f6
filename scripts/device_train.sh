#!/usr/bin/env bash
# One time-boxed training run on a lent GPU (docs/training.md, "A prepared GPU run").
#
#   bash scripts/device_train.sh [-- msf-train options]
#
# LIMIT: the command's limit in seconds (the device tool's timeout_s, default 600); training
# stops MARGIN seconds before it (default 60). Results go to $OUT (set by the device tool;
# runs/device otherwise): fp16 snapshots, log.jsonl, config.json, summary.json. An OUT that
# already holds a run's results is refused unless --overwrite (passed on to device_run); the
# training itself runs in a private scratch folder inside --work, never in --work itself.
# The machine is bare: msfnet is used from this checkout through PYTHONPATH (no install).
set -u
LIMIT=${LIMIT:-600}
MARGIN=${MARGIN:-60}
OUT=${OUT:-runs/device}
ROOT=$(cd "$(dirname "$0")/.." && pwd)
export PYTHONPATH="$ROOT/common/src:$ROOT/runtime/src:$ROOT/synth/src:$ROOT/model/src${PYTHONPATH:+:$PYTHONPATH}"
export PYTHONUNBUFFERED=1
PY=$(command -v python3 || command -v python)
mkdir -p "$OUT"
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,memory.total,utilization.gpu --format=csv
# timeout is the outer bound (the Python watchdog and os._exit come first): TERM makes
# msf-train finish its step and save, KILL follows 5 s later.
timeout -k 5 -s TERM "$((${LIMIT%.*} - ${MARGIN%.*} / 4))" \
    "$PY" -m msfnet.model.device_run --out "$OUT" --limit "$LIMIT" --margin "$MARGIN" "$@"
rc=$?
ls -l "$OUT"
exit $rc
