"""The header every `cosim bench` report starts with: the command line, the date (UTC), the hardware, the commit.

Each benchmark writes ``OUT/<name>.md`` beginning with ``report_header(command)``, so that a report
copied into ``docs/bench/`` (docs/benchmarks.md says how) carries what produced it and where.
``bench_command`` writes the command line back from the options a benchmark ran with.
"""

from __future__ import annotations

import shlex
import subprocess
from datetime import datetime, timezone
from pathlib import Path

from cosim.guards import GuardsOff

# `cosim bench`'s defaults (``cosim.cli``): options left at them are not written into the command line
DEFAULTS = {"out": "out/bench", "quick": False, "repeat": 3, "count": 200, "seed": 0, "steps": 10_000, "arch": "cpu"}


def bench_command(what: str, **options) -> str:
    """The ``cosim bench WHAT ...`` command line that runs ``what`` with ``options`` (the keywords of
    ``cosim.bench.run_bench``, ``out`` the output folder); options at their defaults, None or False are left out."""
    words = ["cosim", "bench", what]
    for key, value in options.items():
        value = str(value) if isinstance(value, Path) else value
        if value is None or value is False or value == [] or DEFAULTS.get(key, object()) == value:
            continue
        flag = "--" + key.replace("_", "-")
        if value is True:
            words.append(flag)
        elif isinstance(value, (list, tuple)):
            for item in value:
                words += [flag, str(item)]
        else:
            words += [flag, str(value)]
    return shlex.join(words)


def git_commit(root: Path | None = None) -> str | None:
    """The short commit of the checkout holding cosim, and whether tracked files differ from it; None outside git."""
    root = root or Path(__file__).resolve().parents[2]

    def git(*args: str) -> str:
        res = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10, check=True)
        return res.stdout.strip()

    try:
        if Path(git("rev-parse", "--show-toplevel")).resolve() != root.resolve():
            return None  # an installed cosim inside some other repository (a virtualenv in a checkout)
        commit = git("rev-parse", "--short", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return None
    return commit + (" with uncommitted changes" if dirty else "")


def report_header(command: str, now: datetime | None = None, guards_off: GuardsOff | None = None) -> str:
    """Markdown lines a report starts with: the command line as its title, then date (UTC), hardware
    (``cosim.hardware.hardware_line``), the cosim commit when cosim runs from a git checkout and the runner's
    guards the benchmark ran without (``cosim.guards``); ends with a blank line."""
    from cosim.hardware import hardware_line

    now = (now or datetime.now(timezone.utc)).astimezone(timezone.utc)
    lines = [f"# `{command}`", "", f"- date: {now:%Y-%m-%d %H:%M} UTC", f"- hardware: {hardware_line()}"]
    commit = git_commit()
    if commit:
        lines.append(f"- cosim: commit {commit}")
    if guards_off is not None:
        lines.append(f"- {guards_off.line()}")
    return "\n".join(lines) + "\n\n"


def markdown_table(rows: list[dict], columns: list[tuple[str, str, str]]) -> list[str]:
    """``rows`` as the lines of a markdown table of (key, header, format) columns (the format's width is dropped)."""
    lines = ["| " + " | ".join(h for _, h, _ in columns) + " |", "|" + "---|" * len(columns)]
    for r in rows:
        cells = [format(r[k], _plain(fmt)) for k, _, fmt in columns]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _plain(fmt: str) -> str:
    """A format spec without alignment and width (``>8.2f`` -> ``.2f``)."""
    spec = fmt.lstrip("<>^=")
    i = 0
    while i < len(spec) and spec[i].isdigit():
        i += 1
    return spec[i:]
