#!/usr/bin/env bash
# Run the fixed radarpc command list from one source tree into one output folder.
#   run_commands.sh TREE OUTDIR
# Every command runs inside OUTDIR with PYTHONPATH=TREE/src and the shared venv's python;
# its stdout/stderr go to OUTDIR/logs/NN_name.out / .err, its exit code to OUTDIR/logs/rc.txt.
# The tiny training configs are read from this script's folder (fft_tiny.yaml, pp_tiny.yaml).
set -u
TREE=$(cd "$1" && pwd)
OUT=$2
HERE=$(cd "$(dirname "$0")" && pwd)
PY=${PY:-python}
mkdir -p "$OUT" && OUT=$(cd "$OUT" && pwd)
mkdir -p "$OUT/logs"
: > "$OUT/logs/rc.txt"
export PYTHONPATH="$TREE/src"
CFG_FFT="$HERE/fft_tiny.yaml"
CFG_PP="$HERE/pp_tiny.yaml"
cd "$OUT"
n=0
run() {  # run NAME ARGS...
    local name=$1; shift
    n=$((n + 1))
    local tag
    tag=$(printf "%02d_%s" "$n" "$name")
    echo "[$tag] radarpc $*" | tee -a logs/commands.txt
    local t0=$SECONDS
    "$PY" -m radarpc "$@" > "logs/$tag.out" 2> "logs/$tag.err"
    local rc=$?
    echo "$tag rc=$rc" >> logs/rc.txt
    echo "    rc=$rc ($((SECONDS - t0)) s)"
}
run sim_tiny simulate radial --out r_tiny --sensor tiny --sequences 6 --frames-per-sequence 6 --seed 1
run sim_s simulate radial --out r_s --sensor radial-s --sequences 3 --frames-per-sequence 4 --seed 2
run pc_tiny pointcloud r_tiny --density 0.05 --out pc_tiny.parquet
run pc_s pointcloud r_s --snr 1.585 --enrich rd3,sector8 --out pc_s.parquet --sparse-rd-out sparse_s
run pc_s05 pointcloud r_s --density 0.05 --out pc_s05.parquet
run show show r_s --frame 2 --density 0.05 --out frame2.png
run info info r_tiny
run sim_colo simulate coloradar --out colo --scenes hallway,outdoor --runs-per-scene 3 --frames 4 --lidar-beams 8 --lidar-azimuth-steps 64
run oscfar baseline os-cfar colo --split test --out preds --quick-tune --max-tune-frames 2
run eval_points evaluate-points preds --data colo --split test
run train_fft train "$CFG_FFT" --data r_s --out run_fft --epochs 1 --num-workers 0 --no-progress
run eval_fft evaluate run_fft --split test
run train_pp train "$CFG_PP" --data r_s --points pc_s05.parquet --out run_pp --epochs 1 --num-workers 0 --no-progress
run eval_pp evaluate run_pp --split test
run export export pc_s05.parquet --out export_pc
