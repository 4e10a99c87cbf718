#!/usr/bin/env bash
# The learning curve (README, "Learning curve"): for the pins and rect families, one seeds=[0,1,2] run per
# number of training parts (5, 10, 20, 50, 100) on the fixed 20 test and 10 validation parts of
# conf/domain/curve.yaml, every run in MLflow, then the table and figure of `pipe report curve`.
# The runs share one folder of identified fits (OUT/identification_fits): the oracles of the test parts and
# gpr's fits of the training parts are computed once, not at every size and seed. It can be stopped and
# started again: a run whose results.json exists is kept, an unfinished one is continued from its
# checkpoints (resume=) or, without any, started over. FAMILIES
# chooses the families (default "pins rect"), e.g. to run them one after the other on separate days or
# side by side on separate machines, and SIZES the numbers of training parts (default "5 10 20 50 100").
# Extra arguments are Hydra overrides for every run.
# EVALUATE_FROM=<folder of a finished curve> evaluates that curve's trained models again (phase=evaluate,
# their checkpoints only read) into OUT instead of training: after a change of the evaluation alone (e.g.
# the identification engine), the same results as a whole new curve in a fraction of its time. Its identified
# fits (named by their inputs' hash, so never stale) are copied into OUT first, so no oracle is fitted again.
# The committed curve (README, docs/learning_curve/) is measured with train.py's defaults of 2026-11-27 (stage 2
# and the evaluation; its stage-1 encoders are those of the curve before it), before the mesh's slices became
# the default: add code.slices=false to come back to it (its baselines chose their input by the plain minimum,
# before the one-standard-error rule). With the slices 5, 10 and 100 parts were run, for both families
# (docs/learning_curve/slices/: SIZES=100 bash scripts/learning_curve.sh runs/curve_slices threads=2, then
# evaluated again with the baselines' one-standard-error rule: EVALUATE_FROM=runs/curve_slices SIZES=100 into
# runs/curve_1se; then SIZES="5 10", then SIZES=20 into runs/curve_1se, one family after the other), and all
# evaluated again once gpr and the blackbox kept the model's standardisation of the hand-made inputs:
# EVALUATE_FROM=runs/curve_1se SIZES="5 10 20" and EVALUATE_FROM=runs/curve_slices SIZES=100 into
# runs/curve_std (a run evaluated from another holds no checkpoints: evaluate from where it was trained);
# then 50 parts trained into runs/curve_std with the present code (FAMILIES="rect pins" SIZES=50 ... threads=2),
# which wrote the report of all five sizes (docs/learning_curve/slices/).
# The curves before come back with
# code.sections=false (docs/learning_curve/no_sections/), code.sections=false stages.vae.force_weight=0
# (docs/learning_curve/force_weight_0/) and code.sections=false stages.head.loss=mse head.hidden=128
# stages.vae.force_weight=0 (stage 2's paper loss and a head of width 128, docs/learning_curve/paper_loss_width128/).
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
