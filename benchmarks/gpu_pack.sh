#!/usr/bin/env bash
# Packs what a GPU check needs into .gpu/ (ignored by git; carry it to the device machine):
#   .gpu/site.tar.xz   Python 3.12 packages the device image lacks: mitsuba 3.9.1 pruned to the
#                      variants rig uses (cuda_ad_mono, llvm_ad_mono, scalar_rgb) to fit the
#                      64 MiB a device call may carry, drjit 1.5.0, OpenEXR, pyserial, pyusb,
#                      miepython (numpy, scipy, numba, matplotlib, yaml, rich are in the image).
#   .gpu/est_session   bench_estimate.py's synthetic session (made here: --keep-session).
#   .gpu/stray/session a bench diagnose session (stray_light-2) with only its base exp3 fit.
#   .gpu/paper_s6.tar.xz the paper simulation's four sigma_t-6 cases on 16384-spp recordings
#                      (bench_paper_sim.py --truth-spp 16384 made them here), their raw
#                      frames and fits left out (12 MB).
# What one device call carries must stay under 64 MiB: name only the files the job needs
# (estimate: site.tar.xz, est_session, stray; paper: site.tar.xz, paper_s6.tar.xz).
# Run from the repository root on a machine with pip and the .venv; then benchmarks/gpu_run.sh
# runs there. Used in session 39 (docs/estimation-log.md).
set -euo pipefail
root=$(pwd)
mkdir -p .gpu
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
  --platform manylinux2014_x86_64 --platform manylinux1_x86_64 -d "$tmp/whl" \
  mitsuba==3.9.1 drjit==1.5.0 OpenEXR==3.5.3 pyserial pyusb miepython==3.3.0
mkdir "$tmp/site"
for w in "$tmp"/whl/*.whl; do (cd "$tmp/site" && unzip -q -o "$w"); done
# Variants rig never selects, headers and stubs: 194 MB unpacked is over the carry limit.
for v in cuda_ad_mono_polarized cuda_ad_rgb cuda_ad_spectral cuda_ad_spectral_polarized \
         llvm_ad_mono_polarized llvm_ad_rgb llvm_ad_spectral llvm_ad_spectral_polarized \
         scalar_spectral scalar_spectral_polarized; do
  rm -f "$tmp"/site/mitsuba/$v.cpython-312-x86_64-linux-gnu.so
done
rm -rf "$tmp"/site/mitsuba/{include,cmake,pkgconfig,mitsuba_stubs}
find "$tmp/site/mitsuba" -name '*.pyi' -delete
(cd "$tmp/site" && tar cf - .) | xz -T0 -6 > .gpu/site.tar.xz
# GPU_PACK=site packs the packages alone (what diagnose256 carries).
if [ "${GPU_PACK:-all}" = site ]; then du -sh .gpu/site.tar.xz; exit 0; fi
# GPU_PACK=bench packs the packages and one bench diagnose session, BENCH_CASE
# (refractive_boundary-1), with only its base fit: gpu_run.sh's bench job (about 47 MB).
if [ "${GPU_PACK:-all}" = bench ]; then
  src=benchmarks/results/diagnose_cases/bench/${BENCH_CASE:-refractive_boundary-1}
  [ -d "$src/session/estimates" ] || { echo "$src/session: no captured session (run bench_diagnose.py --source bench)"; exit 2; }
  (cd "$src" && tar cf - --exclude='session/diagnoses/*' --exclude='session/estimates/*+diagnosis' \
     --exclude=session.lock session) | xz -T0 -6 > .gpu/bench.tar.xz
  du -sh .gpu/site.tar.xz .gpu/bench.tar.xz; exit 0
fi
# GPU_PACK=light packs the packages and the light-engine bench sessions LIGHT_CASES (ids under
# benchmarks/results/diagnose_cases/bench-light-prof8192; default the two boundary sessions that
# ran past 5 min on 2 cores in session 66), each with its base fit only and without the raw
# frames, which no estimate or diagnosis reads: gpu_run.sh's light job (session 67, about 40 MB).
if [ "${GPU_PACK:-all}" = light ]; then
  base=benchmarks/results/diagnose_cases/bench-light-prof8192
  dirs=()
  for c in $(echo "${LIGHT_CASES:-refractive_boundary-2,refractive_boundary+beam_halo}" | tr , ' '); do
    [ -d "$base/$c/session/estimates" ] || { echo "$base/$c/session: no captured session (run bench_diagnose.py --source bench --engine light --profile-spp 8192)"; exit 2; }
    dirs+=("$c/session")
  done
  (cd "$base" && tar cf - --exclude='session/diagnoses/*' --exclude='session/estimates/*+diagnosis' \
     --exclude=session.lock --exclude='session/raw' "${dirs[@]}") \
    | xz -T0 -6 > .gpu/light.tar.xz
  du -sh .gpu/site.tar.xz .gpu/light.tar.xz; exit 0
fi
# GPU_PACK=mietable packs the packages and the paper simulation's Mie-table recordings
# MIETABLE_CASES (default d0.5_s2; bench_paper_sim.py --truth-engine light --truth-phase table
# made them here), without raw frames or fits: gpu_run.sh's mietable job (session 79).
if [ "${GPU_PACK:-all}" = mietable ]; then
  dirs=()
  for c in $(echo "${MIETABLE_CASES:-d0.5_s2}" | tr , ' '); do
    d=${c}_light_mietable
    [ -f benchmarks/results/paper_sim/$d/session/session.yaml ] || { echo "$d: no captured session (run bench_paper_sim.py --truth-engine light --truth-phase table --cases $c)"; exit 2; }
    dirs+=("$d")
  done
  (cd benchmarks/results/paper_sim && tar cf - --exclude='fit_*' --exclude='check_*' --exclude=session.lock \
     --exclude='session/raw' --exclude='cal/raw' --exclude='cal/beam_g.exr' --exclude='session/estimates' "${dirs[@]}") \
    | xz -T0 -9 > .gpu/mietable.tar.xz
  du -sh .gpu/site.tar.xz .gpu/mietable.tar.xz; exit 0
fi
if [ ! -d .gpu/est_session ]; then
  .venv/bin/python benchmarks/bench_estimate.py --keep-session .gpu/est_session --out "$tmp/cpu.json"
fi
src=benchmarks/results/diagnose_cases/bench/stray_light-2/session
if [ -d "$src" ] && [ ! -d .gpu/stray/session ]; then
  mkdir -p .gpu/stray && cp -r "$src" .gpu/stray/
  rm -rf .gpu/stray/session/diagnoses .gpu/stray/session/estimates/*+diagnosis .gpu/stray/session/session.lock
fi
if [ -d benchmarks/results/paper_sim/d0.5_s6_spp16384 ] && [ ! -f .gpu/paper_s6.tar.xz ]; then
  (cd benchmarks/results/paper_sim && tar cf - --exclude='fit_*' --exclude='check_*' --exclude=session.lock \
     --exclude='session/raw' --exclude='cal/raw' --exclude='cal/beam_g.exr' d*_s6_spp16384) \
    | xz -T0 -9 > .gpu/paper_s6.tar.xz
fi
du -sh .gpu "$root"/.gpu/*
