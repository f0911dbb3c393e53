#!/usr/bin/env bash
# The GPU and many-core measurements of `cosim bench mpm`, in one call of a lent GPU machine.
#
#   scripts/device_bench.sh [quick] [STEP ...]   (in the repository root; results under $OUT, default out/device)
#
# That machine has Python 3.12 with numpy, scipy, pyyaml, tqdm, imageio, matplotlib and no package
# registry, so the wheels cosim needs besides come along in .whl/ (git-ignored: `echo /.whl/ >>
# .git/info/exclude`), made here with
#
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#     --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
#     -d .whl taichi==1.7.4 pydantic pydantic-core annotated-types typing-inspection typing-extensions \
#     trimesh dill colorama
#
# and named in the call's carry. SoftMAC, the peer, comes along the same way when .peers/SoftMAC holds
# a checkout of it (`git clone https://github.com/damianliumin/SoftMAC .peers/SoftMAC`, git-ignored with
# `echo /.peers/ >> .git/info/exclude`; only its softmac/engine/ is needed). The script installs the
# wheels into /tmp/site, then runs these steps, each writing its report and CSV under $OUT:
#   gpu      `cosim bench mpm --arch cuda`: 30k, 250k and 2M particles on the GPU;
#   profile  `cosim bench mpm --arch cuda --profile`: Taichi's kernel profiler over the 2M block, each kernel
#            and each of its parallel loops (what bounds the 2M forward and its backward), then over the 30k block
#            (`--particles 30000`: its kernels' time against its wall time says whether launches bound it);
#   contact  `cosim bench contact --arch cuda --repeat 1` (the paper's contact benchmark: 1100 frames, every
#            model and wall, the steps after the first timed), its `--profile` (a grid frame's kernels, launches,
#            host arrays and device tasks: host- or device-bound), then `cosim run scenes/shake_container_2d.yaml
#            --arch cuda` twice (grid contact; run 2 loads run 1's kernels from the cache): wall_time_s, first_step_s;
#   peer     with .peers/SoftMAC, `cosim bench mpm --arch cuda --peer softmac=.peers/SoftMAC`: cosim / SoftMAC
#            on the 30k block in float64, interleaved (SoftMAC's first 3D backward compiles for minutes);
#   threads  `cosim bench mpm --particles 1000000 --threads 1,2,4,8,16 --scatter serial,coloured --quick`:
#            the many-core curve at 1M particles on the machine's CPU cores.
# Steps run in the order given after the optional `quick` (default: gpu profile contact peer threads), each command
# under `timeout ${STEP_S:-280}` so that one slow step cannot take a call's 600 s: with 15 minutes of device
# time, run `gpu profile contact` in one call and `peer threads` in a second if one call cannot hold all.
# `quick` runs the GPU's 30k block only, 100 contact frames and the curve at 100k particles (a rehearsal on
# any machine: pass ARCH=cpu to run the GPU step on the CPU). dartpy is not installed there: MPM-only.
set -uo pipefail
out="${OUT:-out/device}"
arch="${ARCH:-cuda}"
quick=""
if [ "${1:-}" = quick ]; then quick=quick; shift; fi
steps="${*:-gpu profile contact peer threads}"
site=/tmp/site
mkdir -p "$out"
if [ -d .whl ] && [ ! -d "$site/taichi" ]; then
    python3 -m pip install -q --no-index --no-deps --target "$site" .whl/*.whl
fi
export PYTHONPATH="$site:$PWD${PYTHONPATH:+:$PYTHONPATH}"
cosim() { timeout "${STEP_S:-280}" python3 -m cosim.cli "$@"; }
python3 -c "import platform, taichi, numpy; print('python', platform.python_version(), 'taichi', taichi.__version__, 'numpy', numpy.__version__)"
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader 2>/dev/null || echo "no nvidia-smi"
nproc
q() { [ "$quick" = quick ]; }  # the quick variant of a step
for step in $steps; do
    echo "=== $step ($(date -u +%H:%M:%S))"
    case "$step" in
    gpu)
        if q; then cosim bench mpm --arch "$arch" --quick --out "$out/gpu"; else cosim bench mpm --arch "$arch" --out "$out/gpu"; fi ;;
    profile)  # the 2M block (what bounds it), then the 30k block (launch-bound or not: the criterion against SoftMAC)
        if q; then cosim bench mpm --arch "$arch" --profile --quick --out "$out/profile"
        else cosim bench mpm --arch "$arch" --profile --out "$out/profile"; fi
        cosim bench mpm --arch "$arch" --profile --particles 30000 --out "$out/profile30k" ;;
    contact)  # the paper's contact benchmark, then its grid run twice: run 2 loads run 1's kernels from the cache
        frames=1100
        if q; then frames=100; fi
        if q; then cosim bench contact --arch "$arch" --repeat 1 --quick --out "$out/contact"
        else cosim bench contact --arch "$arch" --repeat 1 --out "$out/contact"; fi
        if q; then cosim bench contact --arch "$arch" --profile --quick --out "$out/contact_profile"
        else cosim bench contact --arch "$arch" --profile --out "$out/contact_profile"; fi
        for run in 1 2; do
            cosim run scenes/shake_container_2d.yaml --arch "$arch" --steps "$frames" --quiet --no-preview --out "$out/shake$run" || break
            python3 -c "import json,sys; m=json.load(open(sys.argv[1])); print('shake_container_2d run', sys.argv[2], {k: m[k] for k in ('steps', 'wall_time_s', 'first_step_s', 'kernel_compile_s', 'substeps_total', 'hardware')})" "$out/shake$run/metrics.json" "$run"
        done ;;
    peer)
        if [ ! -d .peers/SoftMAC ]; then echo "no .peers/SoftMAC: peer step skipped"; continue; fi
        if q; then
            cosim bench mpm --arch "$arch" --peer softmac=.peers/SoftMAC --repeat 1 --quick --out "$out/peer"
        else
            cosim bench mpm --arch "$arch" --peer softmac=.peers/SoftMAC --repeat 3 --out "$out/peer"
        fi ;;
    threads)
        if q; then cosim bench mpm --particles 100000 --threads 1,2 --scatter serial,coloured --quick --out "$out/threads"
        else cosim bench mpm --particles 1000000 --threads 1,2,4,8,16 --scatter serial,coloured --quick --out "$out/threads"; fi ;;
    *) echo "unknown step $step (gpu, profile, contact, peer, threads)" ;;
    esac || echo "step $step failed or ran out of time (exit $?)"
done
