#!/usr/bin/env bash
# The CUDA check to run on a lent GPU machine (see tools/device_site.sh): unpack the carried
# dependencies, run the tests that exercise CUDA (and their neighbours) with a GPU present, then each
# benchmark stage on CUDA, writing every result to $OUT as it comes. One stage's timeout does not
# stop the next. Usage there: bash tools/device_check.sh [quick|full] [STAGE...]; the stages default
# to rendering, detection and simulation (~3 min with the tests on an H100); registration
# on CUDA takes longer (its per-candidate baseline alone ~1 min per view in quick mode), so name it
# on its own with a call of its own.
set -u
mode=${1:-quick}
shift || true
stages=("$@")
[ ${#stages[@]} -gt 0 ] || stages=(rendering detection simulation)
out=${OUT:-/tmp/out}
mkdir -p "$out" /tmp/site
t0=$(date +%s)
tar -xJf .whl/site.tar.xz -C /tmp/site
export PYTHONPATH=$PWD/src:/tmp/site NUMBA_CACHE_DIR=/tmp/numba
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
timeout 150 python3 -m pytest -q -p no:cacheprovider -n 12 --timeout 140 -m "not slow" \
    tests/rendering tests/simulation tests/registration/test_similarity.py \
    tests/registration/test_cm_workflows.py tests/detection/test_shipped_detector.py tests/cli/test_bench.py \
    2>&1 | tail -15 | tee "$out/pytest.txt"
echo "tests done at $(( $(date +%s) - t0 )) s"
for stage in "${stages[@]}"; do
    timeout 400 python3 - "$stage" "$mode" "$out" <<'PY' 2>&1 | grep -E "^(rendering|detection|simulation|registration) |Error"
import json, sys, time
if __name__ == "__main__":  # Dask's spawned workers import this again
    import importlib
    stage, mode, out = sys.argv[1:4]
    t = time.perf_counter()
    figures = importlib.import_module(f"fluoronav.{stage}.bench").run(quick=mode == "quick", device="cuda")
    figures["wall_s"] = time.perf_counter() - t
    print(stage, json.dumps(figures), flush=True)
    with open(f"{out}/bench_{stage}_cuda.json", "w") as f:
        json.dump(figures, f)
PY
    echo "$stage done at $(( $(date +%s) - t0 )) s"
done
