#!/usr/bin/env bash
# One command per comparison row of BENCHMARKS.md: our benchmark, then the anchors (the peer
# implementations in ../shared/anchors) on the same workload, each anchor run through the
# anchors' bench_runner.py (waits for an idle machine, records the CPU other processes took).
#
#   benches/compare.sh mpm nh 20k       # section 1: our f32 forward kernels at 1 and 2 threads,
#                                        # then Taichi at 1 and 2 threads and Warp (1 thread)
#   benches/compare.sh mpm fcr 100k     #   materials nh | fcr, sizes 20k (G = 32) | 100k (G = 64)
#   benches/compare.sh simulate nh 100k # section 4: `pipe simulate` (f32) and the same anchors
#   benches/compare.sh raster 100k 800  # section 5: our rasterizer at 2 and 1 threads, then
#                                        # PyTorch at 2 and 1 threads (N 10k | 100k, res 256 | 800)
#
# Environment:
#   ANCHORS_PY   a Python with taichi, warp-lang and torch (the anchors' README sets one up);
#                without it only our side runs
#   ANCHORS_DIR  the anchors' folder (default: ../shared/anchors, relative to the repository)
#   ANCHORS_OUT  where the anchors' JSON lines are appended (default: target/anchors.jsonl)
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$(pwd)
anchors_dir=$(cd "${ANCHORS_DIR:-../shared/anchors}" 2>/dev/null && pwd || true)
out=${ANCHORS_OUT:-$repo/target/anchors.jsonl}

usage() {
  sed -n '2,17p' "$0" | sed 's/^# \{0,1\}//'
  exit 2
}

# Runs one anchor script (arguments after the script name) through bench_runner.py.
anchor() {
  if [[ -z ${ANCHORS_PY:-} ]]; then
    echo "compare.sh: ANCHORS_PY is not set; skipping the anchor $*" >&2
    return
  fi
  if [[ -z $anchors_dir ]]; then
    echo "compare.sh: no anchors folder (ANCHORS_DIR=${ANCHORS_DIR:-../shared/anchors})" >&2
    exit 2
  fi
  mkdir -p "$(dirname "$out")"
  (cd "$anchors_dir" && "$ANCHORS_PY" bench_runner.py "$out" -- "$ANCHORS_PY" "$@")
}

# The anchors' MPM workloads: `material size` checked, then `n g taichi_steps warp_steps`.
check_mpm() {
  [[ ${1:-} == nh || ${1:-} == fcr ]] && [[ ${2:-} == 20k || ${2:-} == 100k ]] || usage
}
workload() {
  case $1 in
    20k) echo 20000 32 100 50 ;;
    100k) echo 100000 64 20 10 ;;
  esac
}

case ${1:-} in
  mpm)
    check_mpm "${2:-}" "${3:-}"
    read -r n g steps warp_steps < <(workload "$3")
    # One timed call = the anchors' timed loop (`--steps` substeps), the state kept in the
    # engine between calls as the anchors keep theirs in their fields.
    MPM_PRECISION=f32 MPM_STEPS=$steps cargo bench -p pipe-mpm --bench mpm -- \
      "${2}_${3}_g${g}" --skip fwd_bwd
    for t in 1 2; do
      anchor mpm_taichi.py --threads "$t" --material "$2" --n "$n" --grid "$g" \
        --steps "$steps" --repeats 3
    done
    anchor mpm_warp.py --material "$2" --n "$n" --grid "$g" --steps "$warp_steps" --repeats 3
    ;;
  simulate)
    check_mpm "${2:-}" "${3:-}"
    # The bench runs the anchors itself, right after each of our runs, when ANCHORS_PY is set.
    ANCHORS_DIR=$anchors_dir PIPE_BENCH_CASES="${2}_${3}" \
      cargo bench -p pipe --bench simulate_anchor
    ;;
  raster)
    case ${2:-}/${3:-} in
      10k/256 | 10k/800) n=10000 repeats=3 ;;
      100k/256 | 100k/800) n=100000 repeats=2 ;;
      *) usage ;;
    esac
    for t in 2 1; do
      RAYON_NUM_THREADS=$t cargo bench -p pipe-render --bench raster
    done
    for t in 2 1; do
      anchor raster_torch.py --threads "$t" --n "$n" --res "$3" --repeats "$repeats"
    done
    ;;
  *) usage ;;
esac
