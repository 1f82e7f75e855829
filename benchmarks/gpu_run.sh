#!/usr/bin/env bash
# Runs on the device machine (one NVIDIA GPU, Python 3.12 image, no network), from the
# repository root with what benchmarks/gpu_pack.sh put in .gpu/ carried. Logs and JSON go to $OUT.
#
#   benchmarks/gpu_run.sh estimate   rig doctor; bench_estimate.py on the kept synthetic session
#                                    (rig picks cuda_ad_mono itself); rig diagnose on the
#                                    stray_light-2 bench session, channel g, its base fit given
#   benchmarks/gpu_run.sh paper      bench_paper_sim.py's four sigma_t-6 cases on their
#                                    16384-spp recordings (.gpu/paper_s6.tar.xz), exp3, at the
#                                    default settings, then with the final / polish renders at
#                                    PAPER_FINAL_SPP (8192); fit seed PAPER_SEED (0)
#   benchmarks/gpu_run.sh diagnose256 the synthetic diagnosis suite on rig estimate's 256-px
#                                    window at 2048 spp from 4096-spp base fits (session 41: what
#                                    that window needs; 20-25 min a case on 2 cores); the cases in
#                                    DIAG_CASES (comma-separated ids, run in that order; default the three spot-checked
#                                    on the CPU), new cases stop after DIAG_BUDGET_S (default 420);
#                                    no data carried beyond site.tar.xz. The case JSONs come back
#                                    in $OUT/diagnose256_cases.tar: unpack into
#                                    benchmarks/results/diagnose_cases/ and run the same command
#                                    here to tabulate; cached cases are not run again.
# Each step runs under `timeout` so the call ends inside the device's 10-minute limit.
# Session 39's calls (device tool `run`): `bash benchmarks/gpu_run.sh estimate` carrying
# [".gpu/site.tar.xz", ".gpu/est_session", ".gpu/stray"] (136 s on an H200), and `PAPER_SEED=1 bash benchmarks/gpu_run.sh paper` carrying
# [".gpu/site.tar.xz", ".gpu/paper_s6.tar.xz"] (235-240 s each); a machine's start adds 1-2 min.
# Session 42's calls on an H100: `DIAG_CASES=refractive_boundary+beam_halo,... DIAG_BUDGET_S=400 DIAG_LIMIT_S=570
# bash benchmarks/gpu_run.sh diagnose256` carrying [".gpu/site.tar.xz"] (one pair case 381 s, singles 13-59 s;
# four calls in the 15 minutes, logs in benchmarks/results/gpu_session42/).
# Session 43's calls on an H100: the same with DIAG_BUDGET_S=430 DIAG_LIMIT_S=540 (465 s, three strong singles) and
# DIAG_BUDGET_S=250 DIAG_LIMIT_S=330 (337 s, two singles; the third, lens_blur-2, was cut by the timeout: the budget
# stops new cases, not a running one, so leave DIAG_LIMIT_S - DIAG_BUDGET_S above the longest case, ~200 s for a single).
# Session 46's calls on an H200: DIAG_SPP=512 DIAG_REFITS=decorrelated
# DIAG_BASE_FROM=synthetic-v11-excess0-spp2048-base4096-cols256 with DIAG_BUDGET_S=300 DIAG_LIMIT_S=520 (370 s, six
# singles) and DIAG_BUDGET_S=230 DIAG_LIMIT_S=420 (384 s, two cases and three pairs), after GPU_PACK=site gpu_pack.sh.
# Session 55's calls on an H200 (after GPU_PACK=bench gpu_pack.sh): `BENCH_LIMIT_S=300 bash benchmarks/gpu_run.sh bench`
# then, in the same call, `DIAG_FRESH=1 DIAG_BASE_FROM=synthetic-v11-excess0-spp2048-base4096-cols256 DIAG_CASES=...
# bash benchmarks/gpu_run.sh diagnose256` carrying [".gpu/site.tar.xz", ".gpu/bench.tar.xz"] (bench 120 s, three cases
# 96 s, 250 s with the start), and the next eight cases with DIAG_LIMIT_S=560 DIAG_BUDGET_S=430 (459 s); logs and
# JSON in benchmarks/results/gpu_session55/.
# Session 56's calls on an H200 (the same packs): the bench job with BENCH_LIMIT_S=240 then six cases in one call
# (the bench job ran out at 240 s there, unfinished, with no log: it prints only at the end; 401 s with the start),
# `BENCH_LIMIT_S=420 bash benchmarks/gpu_run.sh bench` (219 s), then two cases and one case (108 s, 49 s); logs
# and JSON in benchmarks/results/gpu_session56/. Chain the calls: the machine goes back after 30 s idle.
# Session 67's call on an H200 (after GPU_PACK=light gpu_pack.sh, two boundary sessions, 18 MB): `bash
# benchmarks/gpu_run.sh light` carrying [".gpu/site.tar.xz", ".gpu/light.tar.xz"]; results in
# benchmarks/results/gpu_session67/.
# Session 68's call on an H200: `LB_CASES=... LB_LABEL=gpu68 bash benchmarks/gpu_run.sh lightbench` carrying
# [".gpu/site.tar.xz"]; results in benchmarks/results/gpu_session68/.
# Session 79's calls on an H200 (after GPU_PACK=mietable gpu_pack.sh; MIETABLE_CASES for more than d0.5_s2, and
# at most six cases beside site.tar.xz in 64 MiB): `bash benchmarks/gpu_run.sh mietable` (10 s), then
# `MIETABLE_MODELS=expauto` on the two d 0.5 um cases (28 s) and `MIETABLE_MODELS=expauto,exp3` on the other six
# (67 s; the warm machine kept the first cases' fits), carrying [".gpu/site.tar.xz", ".gpu/mietable.tar.xz"];
# results in benchmarks/results/gpu_session79/.
set -uo pipefail
job=${1:-estimate}
OUT=${OUT:-/tmp/gpu_out}; mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
# A second job in the same call finds the packages already unpacked.
[ -f /tmp/site/.unpacked ] || { mkdir -p /tmp/site && tar xJf .gpu/site.tar.xz -C /tmp/site && touch /tmp/site/.unpacked; } || exit 3
export PYTHONPATH=/tmp/site:$(pwd)
nvidia-smi -L
python3 -c "import mitsuba, drjit, numpy, scipy; print('mitsuba', mitsuba.__version__, 'drjit', drjit.__version__, 'numpy', numpy.__version__, 'scipy', scipy.__version__)"
python3 - <<'PY' || { echo "cuda_ad_mono failed"; ldconfig -p | grep -i -E "optix|libcuda"; exit 4; }
from estimate.mitsuba_env import init_mitsuba
print("variant:", init_mitsuba().variant())
PY
t0=$(date +%s)
case $job in
estimate)
  python3 -m rig.cli doctor 2>&1 | tee "$OUT/doctor.log"
  echo "== bench_estimate (GPU) =="
  timeout "${EST_LIMIT_S:-220}" python3 benchmarks/bench_estimate.py --keep-session .gpu/est_session \
    --out "$OUT/bench_estimate_gpu.json" 2>&1 | tee "$OUT/bench_estimate.log"
  echo "== rig diagnose stray_light-2 (GPU) =="
  fit=$(ls .gpu/stray/session/estimates | head -1)
  t=$(date +%s)
  timeout "${DIAG_LIMIT_S:-300}" python3 -m rig.cli diagnose .gpu/stray/session --fit "$fit" --channels g \
    --no-plots --json --no-progress > "$OUT/diagnose_gpu.json" 2> "$OUT/diagnose.log"
  echo "diagnose rc $? wall $(( $(date +%s) - t )) s"
  tail -5 "$OUT/diagnose.log"
  ;;
paper)
  mkdir -p benchmarks/results/paper_sim && tar xJf .gpu/paper_s6.tar.xz -C benchmarks/results/paper_sim || exit 5
  cases=d0.5_s6,d0.3_s6,d0.01_s6,d0.2_s6
  t=$(date +%s)
  timeout "${PAPER_DEFAULT_LIMIT_S:-200}" python3 benchmarks/bench_paper_sim.py --models exp3 --truth-spp 16384 \
    --cases $cases --seed "${PAPER_SEED:-0}" --unbiased --out "$OUT/paper_gpu_default.json" 2>&1 | tee "$OUT/paper_default.log"
  echo "default settings: wall $(( $(date +%s) - t )) s"
  t=$(date +%s)
  timeout "${PAPER_SPP_LIMIT_S:-300}" python3 benchmarks/bench_paper_sim.py --models exp3 --truth-spp 16384 \
    --cases $cases --seed "${PAPER_SEED:-0}" --unbiased --setting final_spp=${PAPER_FINAL_SPP:-8192} \
    --out "$OUT/paper_gpu_spp.json" 2>&1 | tee "$OUT/paper_spp.log"
  echo "final_spp ${PAPER_FINAL_SPP:-8192}: wall $(( $(date +%s) - t )) s"
  # The fits cached so far, also those of a run stopped by its timeout.
  (cd benchmarks/results/paper_sim && tar cf "$OUT/paper_fits.tar" */fit_*.json)
  ;;
diagnose256)
  # DIAG_SPP (2048) and DIAG_REFITS (fixed-seed); DIAG_BASE_FROM names a cache whose base
  # fits are reused (bench_diagnose.py --base-from); DIAG_FRESH=1 reruns cases the cache holds. What comes back is every case JSON this
  # run wrote, whichever cache folder bench_diagnose.py chose for these options.
  spp=${DIAG_SPP:-2048}; refits=${DIAG_REFITS:-fixed-seed}
  base_from=(); [ -n "${DIAG_BASE_FROM:-}" ] && base_from=(--base-from "$DIAG_BASE_FROM")
  mkdir -p benchmarks/results/diagnose_cases && touch "$OUT/.start"
  t=$(date +%s)
  fresh=(); [ -n "${DIAG_FRESH:-}" ] && fresh=(--fresh)
  timeout "${DIAG_LIMIT_S:-560}" python3 benchmarks/bench_diagnose.py --excess 0 --spp "$spp" --base-spp 4096 \
    --columns 256 --refits "$refits" "${base_from[@]}" "${fresh[@]}" --only "${DIAG_CASES:-clean-1,beam_halo-1,beam_halo-2}" \
    --time-budget "${DIAG_BUDGET_S:-420}" --label gpu 2>&1 | tee "$OUT/diagnose256.log"
  echo "diagnose256: wall $(( $(date +%s) - t )) s"
  (cd benchmarks/results/diagnose_cases && find . -name '*.json' -newer "$OUT/.start" -print0 \
     | tar cf "$OUT/diagnose256_cases.tar" --null -T -)
  rm -f "$OUT/.start"
  ;;
bench)
  # rig diagnose on a carried bench session (.gpu/bench.tar.xz: session/ with its base fit only,
  # made by gpu_pack.sh with GPU_PACK=bench), exactly as bench_diagnose.py --source bench runs
  # it on the cores: channel g, --spp BENCH_SPP (256), fixed-seed refits, the estimator's final
  # fit. The diagnosis (diagnosis.yaml, what --json prints) and its refit come back in
  # $OUT/bench_diagnosis.tar; the step log streams to bench_diagnose.log (--json would silence
  # it, and a run cut by the timeout would leave nothing to read: session 56).
  mkdir -p /tmp/bench && tar xJf .gpu/bench.tar.xz -C /tmp/bench || exit 5
  fit=$(ls -d /tmp/bench/session/estimates/*/ | grep -v '+diagnosis' | tail -1)
  t=$(date +%s)
  timeout "${BENCH_LIMIT_S:-300}" python3 -m rig.cli diagnose /tmp/bench/session --fit "$fit" --channels g \
    --spp "${BENCH_SPP:-256}" --no-plots --no-progress > "$OUT/bench_summary.txt" 2> "$OUT/bench_diagnose.log"
  echo "bench diagnose rc $? wall $(( $(date +%s) - t )) s"
  tail -4 "$OUT/bench_diagnose.log"; head -12 "$OUT/bench_summary.txt"
  (cd /tmp/bench/session && tar cf "$OUT/bench_diagnosis.tar" diagnoses $(ls -d estimates/*+diagnosis 2>/dev/null))
  ;;
light)
  # The light engine (the estimator's default since session 61) on a GPU, first run in session 67:
  # bench_estimate.py on a synthetic session made there (the GPU's 8192-spp polish), then
  # `rig diagnose --engine light` at 2048 spp, fixed-seed refits, channel g, as
  # bench_diagnose.py --source bench --engine light runs it, on each bench session that
  # gpu_pack.sh's GPU_PACK=light put in .gpu/light.tar.xz, each under LIGHT_LIMIT_S (170).
  # Back in $OUT: the logs, and light_gpu.tar with every diagnosis' --json ('+' in a case id
  # is not a name $OUT returns, hence the tar).
  mkdir -p /tmp/light /tmp/light_out
  python3 -m rig.cli doctor 2>&1 | tail -4
  echo "== bench_estimate, light engine (GPU) =="
  timeout "${EST_LIMIT_S:-120}" python3 benchmarks/bench_estimate.py --keep-session /tmp/est \
    --out /tmp/light_out/bench_estimate_light_gpu.json 2>&1 | tee "$OUT/bench_estimate_light.log"
  tar xJf .gpu/light.tar.xz -C /tmp/light || exit 5
  for c in $(ls /tmp/light); do
    fit=$(ls -d /tmp/light/$c/session/estimates/*/ | grep -v '+diagnosis' | tail -1)
    echo "== rig diagnose --engine light $c (GPU) =="
    t=$(date +%s)
    timeout "${LIGHT_LIMIT_S:-170}" python3 -m rig.cli diagnose /tmp/light/$c/session --fit "$fit" --channels g \
      --spp "${LIGHT_SPP:-2048}" --refits fixed-seed --engine light --json --no-plots --no-progress \
      > "/tmp/light_out/${c}_diagnose.json" 2> "/tmp/light_out/${c}_diagnose.log"
    echo "$c: rc $? wall $(( $(date +%s) - t )) s"
    tail -3 "/tmp/light_out/${c}_diagnose.log"
    python3 - "/tmp/light_out/${c}_diagnose.json" <<'PY' || true
import json, sys
ch = json.load(open(sys.argv[1]))["channels"]["g"]
print("named", list(ch.get("confirmed_effects") or {}),
      "chi2 at floor", round(ch["reduced_chi2_adjusted_before"], 3), "->", round(ch["reduced_chi2_adjusted_after"], 3),
      "time_s", round(ch["time_s"], 1), "stages", {k: round(v, 1) for k, v in (ch.get("time_by_stage_s") or {}).items()})
PY
  done
  (cd /tmp/light_out && tar cf "$OUT/light_gpu.tar" .)
  ;;
lightbench)
  # The light bench recorded and diagnosed there from scratch, as on the cores:
  # bench_diagnose.py --source bench --engine light --profile-spp 8192 --spp 2048 --fresh on
  # the cases LB_CASES (comma-separated, run in that order), new cases stopped after
  # LB_BUDGET_S (420; the budget stops new cases, not a running one, so leave LB_LIMIT_S above
  # it by the longest case, ~130 s). The report and every case JSON this run wrote come back in
  # $OUT/lightbench.tar ('+' in a case id is not a name $OUT returns); bench_diagnose.py keys
  # its case files without the label, so rename them (e.g. *_gpu68.json) when unpacking beside
  # the cores' files. Session 68: the 10 cases session 67's budget cut, and the compression pair
  # again after session 67's fix.
  mkdir -p benchmarks/results/diagnose_cases && touch "$OUT/.start"
  t=$(date +%s)
  timeout "${LB_LIMIT_S:-560}" python3 benchmarks/bench_diagnose.py --source bench --engine light --profile-spp 8192 \
    --spp 2048 --fresh --only "${LB_CASES:-clean-3}" --time-budget "${LB_BUDGET_S:-420}" --label "${LB_LABEL:-gpu}" \
    2>&1 | tee "$OUT/lightbench.log"
  echo "lightbench: wall $(( $(date +%s) - t )) s"
  (cd benchmarks/results && find . -newer "$OUT/.start" -type f \( -name '*.json' -o -name '*.md' \) \
     -not -path '*/session/*' -print0 | tar cf "$OUT/lightbench.tar" --null -T -)
  rm -f "$OUT/.start"
  ;;
mietable)
  # The fits of degree 5 and more with their fixed-seed Levenberg-Marquardt (session 79) on a
  # GPU: bench_paper_sim.py on the Mie-table recordings .gpu/mietable.tar.xz holds (gpu_pack.sh
  # GPU_PACK=mietable), the models MIETABLE_MODELS (exp7,exp3) at the GPU's defaults (the
  # polish at 8192 spp, the LM at 4 x that), each case under MIETABLE_LIMIT_S (420).
  mkdir -p benchmarks/results/paper_sim && tar xJf .gpu/mietable.tar.xz -C benchmarks/results/paper_sim || exit 5
  cases=$(cd benchmarks/results/paper_sim && ls -d *_light_mietable | sed 's/_light_mietable//' | paste -sd,)
  t=$(date +%s)
  timeout "${MIETABLE_LIMIT_S:-420}" python3 benchmarks/bench_paper_sim.py --truth-engine light --truth-phase table \
    --cases "$cases" --models "${MIETABLE_MODELS:-exp7,exp3}" --unbiased --out "$OUT/mietable_gpu.json" 2>&1 \
    | tee "$OUT/mietable.log"
  echo "mietable: wall $(( $(date +%s) - t )) s"
  (cd benchmarks/results/paper_sim && tar cf "$OUT/mietable_fits.tar" */fit_*.json)
  ;;
*) echo "unknown job $job (estimate, paper, diagnose256, bench, light, lightbench or mietable)"; exit 2 ;;
esac
echo "total $(( $(date +%s) - t0 )) s"
