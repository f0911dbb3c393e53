#!/usr/bin/env bash
# Build a baseline for `cosim bench mpm --baseline DIR`: the code at a past commit,
# installed in its own virtualenv, so that one benchmark run can time it against
# the current code on the same machine.
#
#   scripts/baseline_env.sh [COMMIT] [DIR]      (defaults: b24c315 /tmp/cosim-baseline)
#
# Makes DIR/src (a git worktree of COMMIT, detached) and DIR/venv (python -m venv
# --system-site-packages: taichi, numpy etc. come from this interpreter, so only
# cosim differs), installs DIR/src into the venv with `pip install --no-deps -e`,
# and checks that the venv's python imports cosim from DIR/src, not from another
# editable install (those are .pth files in the system site-packages, which the
# venv also reads). Then: cosim bench mpm --baseline DIR
# Remove with: git worktree remove DIR/src && rm -rf DIR
set -euo pipefail
commit="${1:-b24c315}"
dir="${2:-/tmp/cosim-baseline}"
repo="$(git -C "$(dirname "$0")" rev-parse --show-toplevel)"
python="${PYTHON:-python3}"

if [ -e "$dir" ]; then
    echo "error: $dir exists; remove it first (git -C $repo worktree remove --force $dir/src; rm -rf $dir)" >&2
    exit 1
fi
mkdir -p "$dir"
git -C "$repo" worktree add --detach "$dir/src" "$commit"
"$python" -m venv --system-site-packages "$dir/venv"
# Run from DIR so that no cosim in the current directory is found first.
(cd "$dir" && env -u PYTHONPATH "$dir/venv/bin/python" -m pip install --quiet --no-deps -e "$dir/src")
found="$(cd "$dir" && env -u PYTHONPATH "$dir/venv/bin/python" -c 'import cosim; print(cosim.__file__)')"
case "$found" in
    "$dir/src/"*) echo "baseline ready: $dir/venv/bin/python imports $found (commit $(git -C "$dir/src" rev-parse --short HEAD))" ;;
    *) echo "error: $dir/venv/bin/python imports cosim from $found, not $dir/src" >&2; exit 1 ;;
esac
