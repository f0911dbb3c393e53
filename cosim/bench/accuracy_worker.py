"""One case of the accuracy benchmark, run in a Ray actor (``run_case``) or a child process (``main``).

Taichi initialises once per process with one precision, so the benchmark never runs cases of
two precisions in one process: each precision gets its own Ray actors or its own child process.
A child reads its cases as JSON on stdin and prints one ``MARK``-prefixed JSON line per case as
it finishes (anything else it prints, Taichi's banner for one, is not a result).
"""

from __future__ import annotations

import json
import os
import sys
import time
from numbers import Number

MARK = "ACCURACY_CASE "


def _plain(value):
    """JSON-friendly copies of NumPy numbers and arrays inside ``value``."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if hasattr(value, "tolist"):
        return _plain(value.tolist())
    if isinstance(value, bool) or not isinstance(value, Number):
        return value
    return int(value) if isinstance(value, int) else float(value)


def run_case(problem: str, setting: tuple) -> dict:
    """Problem ``problem`` (a name of ``accuracy_problems.PROBLEMS``) at ``setting`` (the fields of a
    ``Setting``): its observation, with the whole case's wall time ``total_s`` (build and compile
    included) and the machine's 1-minute load average when it ended, ``load1``."""
    from cosim.bench.accuracy_problem import Setting
    from cosim.bench.accuracy_problems import PROBLEMS

    t0 = time.perf_counter()
    out = PROBLEMS[problem].run(Setting(*setting))
    out.update(total_s=time.perf_counter() - t0, load1=os.getloadavg()[0])
    return _plain(out)


def main() -> None:
    """Run the cases [[problem, setting], ...] given on stdin, in order, one result line each."""
    cases = json.loads(sys.stdin.read())
    for index, (problem, setting) in enumerate(cases):
        try:
            result = {"index": index, "ok": True, "value": run_case(problem, tuple(setting))}
        except Exception as exc:  # noqa: BLE001 - a failing case is its result; the others go on
            result = {"index": index, "ok": False, "value": f"{type(exc).__name__}: {exc}"}
        print(MARK + json.dumps(result), flush=True)


if __name__ == "__main__":
    main()
