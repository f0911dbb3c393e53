#!/usr/bin/env bash
# The packaging check of .ci/run: a plain (not editable) install must work on its own.
#
#   scripts/check_install.sh        (PYTHON=... to use another interpreter; default: python)
#
# Builds the wheel from a copy of the files git sees (tracked, or untracked and not ignored), checks that it holds every package and scene
# file (scripts/check_wheel.py), installs it with --no-deps into a venv made with
# --system-site-packages (the dependencies come from this interpreter: nothing is downloaded twice),
# checks that the venv imports cosim from the wheel, not from the checkout or an editable install,
# and runs that cosim from outside the checkout: on the shipped scenes whose losses read
# scenes/assets/*_target.npz (squeeze_plasticine's fingers reach the block after ~50 steps, so its
# 2-step gradient is zero: it checks that the target loads and the Chamfer loss runs both ways), and a
# gradient check that resolves something in 2 steps (elastic_bounce_2d: initial velocities and impulses).
# Everything lies in a mktemp -d folder, removed at the end.
set -euo pipefail
repo="$(cd "$(dirname "$0")/.." && pwd)"
python="${PYTHON:-python}"
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
start=$SECONDS

mkdir "$tmp/src"
(cd "$repo" && git ls-files -z -co --exclude-standard | tar --null --ignore-failed-read -T - -cf -) | tar -xf - -C "$tmp/src"
"$python" -m pip wheel --quiet --no-deps -w "$tmp/dist" "$tmp/src"
wheel="$(echo "$tmp"/dist/cosim-*.whl)"
echo "wheel: $(basename "$wheel"), $(du -k "$wheel" | cut -f1) KiB"
"$python" "$repo/scripts/check_wheel.py" "$wheel"

"$python" -m venv --system-site-packages --without-pip "$tmp/venv"
"$python" -m pip --python "$tmp/venv/bin/python" install --quiet --no-deps "$wheel"
cd "$tmp"
unset PYTHONPATH
found="$("$tmp/venv/bin/python" -c 'import cosim.scenes as s; print(s.__file__)')"
echo "the venv's cosim.scenes: $found"
if [[ "$found" != "$tmp/venv/"* ]]; then
    echo "error: the venv imports cosim from $found, not from the wheel" >&2
    exit 1
fi
"$tmp/venv/bin/cosim" validate make_taco
"$tmp/venv/bin/cosim" gradcheck squeeze_plasticine --steps 2
"$tmp/venv/bin/cosim" gradcheck elastic_bounce_2d --steps 2
echo "packaging check passed in $((SECONDS - start)) s"
