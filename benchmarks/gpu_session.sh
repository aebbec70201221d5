#!/usr/bin/env bash
# Every GPU number of issue 32 in one lease of a device: the kernels checked against XLA on the device, then
# benchmarks/gpu.py with the tables' choice (next to Taichi CUDA), 3D on the XLA kernel, the Pallas kernel
# unsorted in 2D and 3D, the XLA kernel summing over the stencil's slots as one reduction (--stencil-sum
# reduce, not yet timed), and the scheme / gradient (auto, and two levels) / ensemble parts.  Each stage has its own time limit, so
# one slow stage cannot take the others' time; every row is printed as it is measured (the log is the record
# if a stage is cut).
#
#   bash benchmarks/gpu_session.sh OUT_DIR          # OUT_DIR receives log.txt, gpu.md and gpu.csv
#   GPU_SESSION_EXTRA=--quick bash benchmarks/gpu_session.sh /tmp/dry   # the same stages at small sizes (a CPU)
#
# Taichi is not a dependency: where pip cannot reach an index, carry its wheel (and dill's) in .whl/ and this script
# installs them to /tmp/site first.
set -u
out=${1:-benchmarks/results/gpu_session}
mkdir -p "$out"
export PYTHONUNBUFFERED=1
if ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl/*.whl \
    && export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
fi
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
log=$out/log.txt
{
  nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
  python3 -c "import jax, jaxmpm; print('jax', jax.__version__, jax.devices())"
  # the Pallas kernel on the device (Triton, not interpret mode) against the XLA kernel, float64 and float32
  timeout 45 python3 -m pytest -q -p no:cacheprovider tests/test_pallas_kernel.py \
    -k "float32_equals or simulation_steps_equal" -m "not slow" 2>&1 | tail -4
  stage() {  # stage NAME SECONDS ARGS...: one benchmarks/gpu.py run into $out/NAME
    local name=$1 seconds=$2; shift 2
    echo "=== $name (limit ${seconds} s): benchmarks/gpu.py $*"
    timeout "$seconds" python3 benchmarks/gpu.py --repeats 2 --out "$out/$name" "$@" ${GPU_SESSION_EXTRA:-} 2>&1 \
      | grep -v "^\[Taichi\]"
  }
  stage auto 170 --parts mpm88 mpm3d
  # the same from the fluid piled up on the floor (the default window is mpm88's free fall: the particles spread out)
  stage settled 60 --parts mpm88 --sizes 131072 2097152 --settle 2500
  stage xla 50 --parts mpm3d --kernel xla --no-taichi
  stage pallas 70 --parts mpm3d mpm88 --kernel pallas --sort-every 0 --no-taichi
  stage stencil_sum 60 --parts mpm88 mpm3d --kernel xla --stencil-sum reduce --no-taichi
  stage schemes 75 --parts schemes --no-taichi
  stage gradient 65 --parts gradient --no-taichi
  stage gradient_two_levels 65 --parts gradient --no-taichi --checkpoint true  # "auto" keeps every step's state
  # the gradient's steps differentiated in chunks, each recomputed in the reverse pass (the CPU's default from 24k
  # particles in 2D; DERIVATIVE_CHUNK_TABLE's GPU row is unmeasured: the whole step's derivatives)
  stage gradient_chunks 65 --parts gradient --no-taichi --derivative-chunk-particles 16384
  stage ensemble 50 --parts ensemble --no-taichi
  # the step over its particles in chunks (the CPU's default in 2D from 60k-100k particles, in 3D from 16k-32k;
  # CHUNK_TABLE's GPU row is unmeasured): time and program bytes per particle against the whole step's rows of the "auto" stage
  stage chunks 60 --parts mpm88 --sizes 524288 2097152 --chunk-particles 262144 --no-taichi
  # sim.run with runtime frame and step counts against static scans: RUNTIME_COUNTS's GPU row (static scans, unmeasured)
  echo "=== run_counts (limit 120 s): benchmarks/run_counts.py"
  timeout 120 python3 benchmarks/run_counts.py ${GPU_SESSION_EXTRA:-} 2>&1
  # program bytes per particle against the state's (issue 32 item 7), compiled only: the library's step, the whole
  # step, and chunks of 65536 particles
  echo "=== memory (limit 90 s): benchmarks/memory_per_particle.py --chunks 65536"
  timeout 90 python3 benchmarks/memory_per_particle.py --chunks 65536 --csv "$out/memory_per_particle.csv" \
    ${GPU_SESSION_EXTRA:-} 2>&1
} 2>&1 | tee "$log"
# one table and one CSV for the stages that finished
cat "$out"/*/gpu.md > "$out/gpu.md" 2>/dev/null
head -1 -q "$out"/*/gpu.csv 2>/dev/null | head -1 > "$out/gpu.csv"
for f in "$out"/*/gpu.csv; do tail -n +2 "$f" >> "$out/gpu.csv"; done 2>/dev/null
rm -rf "${out:?}"/*/
