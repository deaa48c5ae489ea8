#!/usr/bin/env bash
# The benchmark protocol end to end, resumable (re-run it after an interruption):
#   1. data:     the dataset of config/benchmark.yaml (train 48 / validate 4 / test 8 scenarios)
#   2. train:    each model's two stages (ego, then fusion from it) on `train`, for every seed; a single-agent
#                preset (a Table 2 baseline: tiny-occformer, tiny-sscnet, ...; or tiny-sscnet-early, the
#                early-fusion reference) has its one stage only
#   3. evaluate: every trained model on `test`, with 95 % intervals over test scenarios, the
#                collaboration, collaborators, pose-noise and input-control ablations
#   4. report:   src/co3sop_nodes/doc/results.md from the evaluation JSON (no hand-typed figure)
#
#   ros2_ws/run_protocol.sh [data|train|evaluate|report ...]      (default: all four, in order)
#
# Settings (environment): DATA (data/bench), RUNS (runs/bench), RESULTS (src/co3sop_nodes/doc/
# evaluation: the JSON behind results.md is committed), PRESETS ("tiny-lidar"), RANGES ("51.2m 76.8m"),
# SEEDS ("1 2 3"; the first only beyond 51.2 m), EGO_STEPS (1200), FUSION_STEPS (2400), SCHEDULE (constant),
# FIRST_SEED_ABLATIONS ("inputs collaborators pose-noise distance": only for the first seed; every seed gets
# collaboration and its ego stage alone), TAG (none: appended as -TAG to each run's folder under RESULTS, so a
# second recipe of the same preset, range and seed, trained under another RUNS, is kept beside the first).
# Choices of steps and presets were made on `validate`;
# `test` is only evaluated here. CPU by default; `--device` follows `DEVICE` (auto).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
"$ROOT/ros2_ws/bootstrap.sh"
# shellcheck disable=SC1091
. "$ROOT/ros2_ws/env.sh"
cd "$ROOT"
LIB="$(python -c 'from ament_index_python.packages import get_package_prefix as p; print(p("co3sop_nodes"))')/lib/co3sop_nodes"
SHARE="$(python -c 'from ament_index_python.packages import get_package_share_directory as p; print(p("co3sop_nodes"))')"
DATA="${DATA:-data/bench}" RUNS="${RUNS:-runs/bench}" RESULTS="${RESULTS:-src/co3sop_nodes/doc/evaluation}"
FIRST_SEED_ABLATIONS="${FIRST_SEED_ABLATIONS-inputs collaborators pose-noise distance}"
PRESETS="${PRESETS:-tiny-lidar}" RANGES="${RANGES:-51.2m 76.8m}" SEEDS="${SEEDS:-1 2 3}"
EGO_STEPS="${EGO_STEPS:-1200}" FUSION_STEPS="${FUSION_STEPS:-2400}" SCHEDULE="${SCHEDULE:-constant}" DEVICE="${DEVICE:-auto}"
STEPS=("$@")
[ ${#STEPS[@]} -gt 0 ] || STEPS=(data train evaluate report)

say() { echo "[protocol] $*"; }

# the runs: preset, range, seed (every seed at 51.2 m, the first seed at the other ranges)
runs() {
  local first
  first="${SEEDS%% *}"
  for preset in $PRESETS; do
    for range in $RANGES; do
      for seed in $SEEDS; do
        if [ "$range" = "51.2m" ] || [ "$seed" = "$first" ]; then echo "$preset $range $seed"; fi
      done
    done
  done
}

# steps DIR: the steps DIR/state.pt has done (0 without one)
steps() {
  python -c 'import sys, torch; print(torch.load(sys.argv[1], weights_only=True, map_location="cpu")["step"])' "$1/state.pt" 2>/dev/null || echo 0
}

# single PRESET: whether the preset has no fusion (a single-agent baseline, trained in one stage)
single() {
  python -c 'import sys; from co3sop_nodes.model.config import preset; sys.exit(0 if not preset(sys.argv[1]).fusion else 1)' "$1"
}

# early PRESET: whether the preset merges the collaborators' scans before one network (scored off / on like fusion)
early() {
  python -c 'import sys; from co3sop_nodes.model.config import preset; sys.exit(0 if preset(sys.argv[1]).early_fusion else 1)' "$1"
}

# train STEPS ARGS... --out DIR: skipped when DIR has done STEPS (or has a model and no state), resumed (or
# extended: a finished run given more steps continues the same sample order) when DIR/state.pt exists
train() {
  local want="$1" out="${*: -1}"
  shift
  if [ -f "$out/model.pt" ] && { [ ! -f "$out/state.pt" ] || [ "$(steps "$out")" -ge "$want" ]; }; then say "$out: trained"; return; fi
  if [ -f "$out/state.pt" ]; then "$LIB/train" "$@" --steps "$want" --resume; else "$LIB/train" "$@" --steps "$want"; fi
}

for step in "${STEPS[@]}"; do
  case "$step" in
    data)
      "$LIB/generate" --recipe "$SHARE/config/benchmark.yaml" --out "$DATA" ;;
    train)
      runs | while read -r preset range seed; do
        run="$RUNS/$preset-$range-s$seed"
        if single "$preset"; then
          train "$EGO_STEPS" --data "$DATA" --preset "$preset" --range "$range" --stage ego --seed "$seed" \
            --schedule "$SCHEDULE" --device "$DEVICE" --out "$run"
          continue
        fi
        train "$EGO_STEPS" --data "$DATA" --preset "$preset" --range "$range" --stage ego --seed "$seed" \
          --schedule "$SCHEDULE" --device "$DEVICE" --out "$run-ego"
        train "$FUSION_STEPS" --data "$DATA" --stage fusion --init "$run-ego/model.pt" --seed "$seed" \
          --schedule "$SCHEDULE" --device "$DEVICE" --out "$run"
      done ;;
    evaluate)
      # one marker per evaluation, so an interrupted step resumes where it stopped; a model trained (or
      # extended) after its marker is evaluated again
      runs | while read -r preset range seed; do
        run="$RUNS/$preset-$range-s$seed" out="$RESULTS/$preset-$range-s$seed${TAG:+-$TAG}"
        if single "$preset" && ! early "$preset"; then  # alone, and the input controls for the first seed
          if [ ! "$out/.done-alone" -nt "$run/model.pt" ]; then
            "$LIB/evaluate" --model "$run/model.pt" --collaborators 0 --data "$DATA" --splits test --device "$DEVICE" --out "$out/alone"
            touch "$out/.done-alone"
          fi
          if [ "$seed" = "${SEEDS%% *}" ] && [ ! "$out/.done-inputs" -nt "$run/model.pt" ]; then
            "$LIB/evaluate" --model "$run/model.pt" --data "$DATA" --splits test --device "$DEVICE" --out "$out" --ablation inputs
            touch "$out/.done-inputs"
          fi
          continue
        fi
        ablations=(collaboration)
        # shellcheck disable=SC2206
        [ "$seed" = "${SEEDS%% *}" ] && ablations+=($FIRST_SEED_ABLATIONS)
        for ablation in "${ablations[@]}"; do
          if [ "$out/.done-$ablation" -nt "$run/model.pt" ]; then say "$out: $ablation evaluated"; continue; fi
          "$LIB/evaluate" --model "$run/model.pt" --data "$DATA" --splits test --device "$DEVICE" --out "$out" --ablation "$ablation"
          touch "$out/.done-$ablation"
        done
        single "$preset" && continue  # early fusion: no ego stage to score
        if [ ! "$out/.done-ego-stage" -nt "$run-ego/model.pt" ]; then
          "$LIB/evaluate" --model "$run-ego/model.pt" --collaborators 0 --data "$DATA" --splits test --device "$DEVICE" --out "$out/ego-stage"
          touch "$out/.done-ego-stage"
        fi
      done ;;
    report)
      "$LIB/report" "$RESULTS" --out src/co3sop_nodes/doc/results.md --goals src/co3sop_nodes/config/benchmark.yaml ;;
    *) echo "run_protocol: unknown step '$step' (data, train, evaluate, report)" >&2; exit 2 ;;
  esac
done
