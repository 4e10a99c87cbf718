#!/usr/bin/env bash
# Regenerate docs/figures/mlflow_runs.png from a real `mlflow ui` session on this repository's store.
# Needs Debian's chromium (`apt-get install chromium`).
# Usage: bash scripts/mlflow_screenshot.sh [out.png] [runs|compare]
#   runs:    the experiment's runs table
#   compare: MLflow's run comparison of the latest finished run of each domain (params and metrics side by side)
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-docs/figures/mlflow_runs.png}
page=${2:-runs}
store=${MLFLOW_TRACKING_URI:-sqlite:///$PWD/mlflow.db}
port=${PORT:-5055}   # WINDOW=width,height sets the browser window (default 1700,950)
log=$(mktemp)
.venv/bin/mlflow ui --backend-store-uri "$store" --host 127.0.0.1 --port "$port" > "$log" 2>&1 &
ui=$!
trap 'kill $ui 2>/dev/null || true; rm -f "$log"' EXIT
for _ in $(seq 60); do curl -sf "http://127.0.0.1:$port/health" > /dev/null && break; sleep 1; done
experiment=$(MLFLOW_TRACKING_URI=$store .venv/bin/python -c \
  "import mlflow; print(mlflow.get_experiment_by_name('pipe').experiment_id)")
url="http://127.0.0.1:$port/#/experiments/$experiment/runs"
if [ "$page" = compare ]; then
  runs=$(MLFLOW_TRACKING_URI=$store .venv/bin/python -c "
import json, mlflow
runs = mlflow.search_runs(experiment_names=['pipe'], filter_string=\"attributes.status = 'FINISHED'\",
                          order_by=['attributes.start_time DESC'])
latest = runs.drop_duplicates('tags.domain')
print(json.dumps(list(latest.sort_values('tags.domain').run_id)))")
  url="http://127.0.0.1:$port/#/compare-runs?runs=$runs&experiments=[\"$experiment\"]"
fi
profile=$(mktemp -d)
chromium --headless --no-sandbox --disable-gpu --disable-quic --no-first-run --disable-background-networking \
  --disable-component-update --disable-sync --user-data-dir="$profile" --window-size="${WINDOW:-1700,950}" \
  --virtual-time-budget=20000 --screenshot="$out" "$url" \
  2> /dev/null
rm -rf "$profile"
echo "wrote $out"
