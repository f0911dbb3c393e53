"""Check a built cosim wheel against the source tree: it must hold every file under cosim/
(the packages and their modules) and under scenes/ (as cosim/scenes/: the scenes and their assets),
and nothing else there (a stale build/ or a __pycache__).

    python scripts/check_wheel.py DIST/cosim-0.1.0-py3-none-any.whl [--repo DIR]

The expected files come from ``git ls-files -co --exclude-standard`` in DIR (default: this checkout):
the tracked files and the untracked ones that are not ignored. Prints what is missing
or extra and exits 1 if anything is.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import zipfile
from pathlib import Path


def expected(repo: Path) -> set[str]:
    """The paths that the wheel must hold: the files under cosim/ and scenes/ that git tracks or would
    (untracked, not ignored), as the working tree has them."""
    out = subprocess.run(
        ["git", "-C", str(repo), "ls-files", "-z", "-co", "--exclude-standard", "--", "cosim", "scenes"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    paths = [p for p in out.split("\0") if p and (repo / p).is_file()]
    return {f"cosim/{p}" if p.startswith("scenes/") else p for p in paths}


def compare(wheel: Path, repo: Path) -> tuple[list[str], list[str], int]:
    """(missing, extra, n): expected paths the wheel lacks, its files under cosim/ that are not expected,
    and the number expected."""
    with zipfile.ZipFile(wheel) as z:
        have = {n for n in z.namelist() if n.startswith("cosim/") and not n.endswith("/")}
    want = expected(repo)
    return sorted(want - have), sorted(have - want), len(want)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("wheel", type=Path)
    ap.add_argument("--repo", type=Path, default=Path(__file__).resolve().parents[1])
    args = ap.parse_args(argv)
    missing, extra, n = compare(args.wheel, args.repo)
    for path in missing:
        print(f"missing from {args.wheel.name}: {path}")
    for path in extra:
        print(f"not in the source tree: {path}")
    if missing or extra:
        print("fix the package list (setup.py) or the package data (pyproject.toml)", file=sys.stderr)
        return 1
    print(f"{args.wheel.name}: all {n} files of cosim/ and scenes/, nothing else")
    return 0


if __name__ == "__main__":
    sys.exit(main())
