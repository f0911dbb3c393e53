"""scripts/check_wheel.py (run by .ci/run on the built wheel) catches a wheel that misses a scene
asset or holds a stray file; a fake wheel stands in for a build (seconds saved)."""

import runpy
import subprocess
import sys
import zipfile

from conftest import ROOT

SCRIPT = ROOT / "scripts" / "check_wheel.py"
TARGET = "cosim/scenes/assets/make_taco_target.npz"


def check(tmp_path, names) -> subprocess.CompletedProcess:
    wheel = tmp_path / "cosim-0.1.0-py3-none-any.whl"
    with zipfile.ZipFile(wheel, "w") as z:
        for name in [*names, "cosim-0.1.0.dist-info/RECORD"]:
            z.writestr(name, "")
    return subprocess.run([sys.executable, SCRIPT, wheel], check=False, capture_output=True, text=True)


def test_check_wheel_lists_what_the_wheel_misses_or_adds(tmp_path):
    want = runpy.run_path(str(SCRIPT))["expected"](ROOT)
    assert TARGET in want and "cosim/losses/__init__.py" in want and "cosim/scenes/make_taco.yaml" in want
    assert check(tmp_path, want).returncode == 0
    short = check(tmp_path, want - {TARGET} | {"cosim/scenes/__pycache__/x.pyc"})
    assert short.returncode == 1
    assert short.stdout.splitlines() == [
        f"missing from cosim-0.1.0-py3-none-any.whl: {TARGET}",
        "not in the source tree: cosim/scenes/__pycache__/x.pyc",
    ]
