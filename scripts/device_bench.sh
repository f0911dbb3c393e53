#!/usr/bin/env bash
# The GPU and many-core measurements of `cosim bench mpm`, in one call of a lent GPU machine.
#
#   scripts/device_bench.sh [quick]      (run in the repository root; results under $OUT, default out/device)
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
# wheels into /tmp/site, then runs, each writing its report and CSV under $OUT:
#   1. `cosim bench mpm --arch cuda`: 30k, 250k and 2M particles on the GPU;
#   2. with .peers/SoftMAC, `cosim bench mpm --arch cuda --peer softmac=.peers/SoftMAC`: cosim / SoftMAC
#      on the 30k block in float64, interleaved (its first 3D backward compiles for minutes);
#   3. `cosim run scenes/shake_container_2d.yaml --arch cuda` twice (the paper's contact benchmark, 1100 frames, grid
#      contact; the second run's kernels come from the first's cache): metrics.json's wall_time_s;
#   4. `cosim bench mpm --particles 1000000 --threads 1,2,4,8,16 --scatter serial,coloured --quick`:
#      the many-core curve at 1M particles on the machine's CPU cores.
# `quick` runs the GPU's 30k block only and the curve at 100k particles (a rehearsal on any machine:
# pass ARCH=cpu to run step 1 on the CPU). dartpy is not installed there: these are MPM-only.
set -euo pipefail
out="${OUT:-out/device}"
arch="${ARCH:-cuda}"
quick="${1:-}"
site=/tmp/site
mkdir -p "$out"
if [ -d .whl ] && [ ! -d "$site/taichi" ]; then
    python3 -m pip install -q --no-index --no-deps --target "$site" .whl/*.whl
fi
export PYTHONPATH="$site:$PWD${PYTHONPATH:+:$PYTHONPATH}"
cosim() { python3 -m cosim.cli "$@"; }
python3 - <<'EOF'
import platform, taichi, numpy
print(f"python {platform.python_version()}, taichi {taichi.__version__}, numpy {numpy.__version__}")
EOF
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader 2>/dev/null || echo "no nvidia-smi"
nproc
contact_benchmark() {  # $1: steps
    for run in 1 2; do
        cosim run scenes/shake_container_2d.yaml --arch "$arch" --steps "$1" --quiet --no-preview --out "$out/shake$run" || return 0
        python3 -c "import json,sys; m=json.load(open(sys.argv[1])); print('shake_container_2d run', sys.argv[2], {k: m[k] for k in ('steps', 'wall_time_s', 'kernel_compile_s', 'substeps_total', 'hardware')})" "$out/shake$run/metrics.json" "$run"
    done
}
if [ "$quick" = quick ]; then
    cosim bench mpm --arch "$arch" --quick --out "$out/gpu"
    [ -d .peers/SoftMAC ] && { cosim bench mpm --arch "$arch" --peer softmac=.peers/SoftMAC --quick --repeat 1 --out "$out/peer" || echo "peer run failed"; }
    contact_benchmark 100
    cosim bench mpm --particles 100000 --threads 1,2 --scatter serial,coloured --quick --out "$out/threads"
else
    cosim bench mpm --arch "$arch" --out "$out/gpu"
    [ -d .peers/SoftMAC ] && { cosim bench mpm --arch "$arch" --peer softmac=.peers/SoftMAC --repeat 3 --out "$out/peer" || echo "peer run failed"; }
    contact_benchmark 1100
    cosim bench mpm --particles 1000000 --threads 1,2,4,8,16 --scatter serial,coloured --quick --out "$out/threads"
fi
