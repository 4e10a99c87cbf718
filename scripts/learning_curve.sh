#!/usr/bin/env bash
# The learning curve (README, "Learning curve"): for the pins and rect families, one seeds=[0,1,2] run per
# number of training parts (5, 10, 20, 50, 100) on the fixed 20 test and 10 validation parts of
# conf/domain/curve.yaml, every run in MLflow, then the table and figure of `pipe report curve`.
# The runs share one folder of identified fits (OUT/identification_fits): the oracles of the test parts and
# gpr's fits of the training parts are computed once per seed, not again at every size. It can be stopped and
# started again: a run whose results.json exists is kept, an unfinished one is continued from its
# checkpoints (resume=) or, without any, started over. FAMILIES
# chooses the families (default "pins rect"), e.g. to run them one after the other on separate days or
# side by side on separate machines, and SIZES the numbers of training parts (default "5 10 20 50 100").
# Extra arguments are Hydra overrides for every run.
# EVALUATE_FROM=<folder of a finished curve> evaluates that curve's trained models again (phase=evaluate,
# their checkpoints only read) into OUT instead of training: after a change of the evaluation alone (e.g.
# the identification engine), the same results as a whole new curve in a fraction of its time. Its identified
# fits (named by their inputs' hash, so never stale) are copied into OUT first, so no oracle is fitted again.
# A folder of evaluations (no checkpoints) is followed back to the folder they evaluated (train.py does that).
# Which commands made the committed curves, and which overrides bring the earlier ones back: README,
# "Learning curve", and docs/results-history.md.
#   [FAMILIES=pins] bash scripts/learning_curve.sh OUT [overrides...]       e.g. OUT = runs/curve
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:?give an output folder, e.g. runs/curve}
shift
mkdir -p "$out"
fits="$(realpath "$out")/identification_fits"
if [ -n "${EVALUATE_FROM:-}" ]; then
    if [ "$(realpath "$EVALUATE_FROM")" = "$(realpath "$out")" ]; then
        echo "EVALUATE_FROM must name another folder than OUT ($out): its runs are read, OUT's replaced" >&2
        exit 2
    fi
    if [ -d "$EVALUATE_FROM/identification_fits" ]; then
        mkdir -p "$fits"
        cp -r "$EVALUATE_FROM/identification_fits/." "$fits/"
    fi
fi
read -ra families <<< "${FAMILIES:-pins rect}"
read -ra sizes <<< "${SIZES:-5 10 20 50 100}"
for family in "${families[@]}"; do
    for count in "${sizes[@]}"; do
        run="$out/$family/train_$count"
        [ -f "$run/results.json" ] && continue
        trained=()
        if [ -n "${EVALUATE_FROM:-}" ]; then
            rm -rf "$run"
            trained=(phase=evaluate "resume=$EVALUATE_FROM/$family/train_$count")
        elif [ -n "$(find "$run" -name '*.ckpt' -print -quit 2>/dev/null)" ]; then
            trained=("resume=$run")
        else
            rm -rf "$run"
        fi
        .venv/bin/python train.py data=family "data.generate.family=$family" domain=curve \
            "domain.train_count=$count" 'seeds=[0,1,2]' "hydra.run.dir=$run" trainer.progress_bar=false \
            "evaluation.identification.cache=$fits" "${trained[@]}" "$@"
    done
done
.venv/bin/pipe report curve "${families[@]/#/$out/}" --out "$out"
