"""A command that runs without some of the runner's guards says so once in its output, in its report's header
and in its CSV (cosim.guards); here `cosim bench contact` and `cosim bench mpm` through ``run_bench`` (the
CLI's path), their simulations replaced by made-up results."""

from __future__ import annotations

import csv
import math

import pytest
from conftest import make_scene

from cosim.errors import SimulationError
from cosim.guards import measure_only
from cosim.scene.build import build_system


def _guard_lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if "guards off" in line]


def test_the_contact_benchmark_says_it_runs_without_the_energy_and_tunnelling_guards(tmp_path, monkeypatch, capsys):
    import cosim.runtime
    from cosim.bench import contact, run_bench

    def made_up(steps, repeat, workers, address, arch):
        rows = [
            {"model": m, "k": f"{k:g}" if k else "", "thickness": f"1/{round(1 / t)}", "penetrated": 0, "in_wall": 0,
             "rebound": 0, "seconds": 1.0, "energy_excess": -0.01}
            for t in contact.THICKNESSES for m, k in contact.RUNS
        ]  # fmt: skip
        return [rows] * repeat

    class Tracked:
        steps = 1

        def __init__(self, *args, **kwargs):
            pass

        def advance(self, frames):
            pass

        def result(self):
            return {}

    monkeypatch.setattr(cosim.runtime, "ensure_taichi", lambda *a, **k: None)
    monkeypatch.setattr(contact, "run_tables", made_up)
    monkeypatch.setattr(contact, "ContainerRun", Tracked)
    monkeypatch.setattr(contact, "_figure", lambda rows, path: None)
    out = tmp_path / "bench"
    assert run_bench("contact", out, quick=True, repeat=1) == 0
    line = "guards off: energy budget, tunnelling (measured, not enforced: the benchmark counts leaks and rebounds)"
    assert _guard_lines(capsys.readouterr().out) == [line, f"- {line}"]  # said at the start; the report printed
    assert _guard_lines((out / "contact.md").read_text()) == [f"- {line}"]
    rows = list(csv.DictReader((out / "contact.csv").open()))
    assert {r["guards_off"] for r in rows} == {"energy budget; tunnelling"}


def test_the_mpm_benchmark_says_its_engine_runs_without_the_runners_checks(tmp_path, monkeypatch, capsys):
    from cosim.bench import mpm, run_bench

    row = {"dim": 2, "precision": "float32", "grid": "32^2", "particles": 100, "steps": 10, "arch": "cpu",
           "threads": 2, "scatter": "serial", "fwd_Mpss": 1.0, "fwd_bwd_Mpss": 0.5, "bwd_fwd_ratio": 2.0,
           "fb_over_fwd": 3.0, "peak_MiB": 100.0, "field_MiB": 10.0, "device_MiB": float("nan"),
           "fwd_B_per_particle": 1.0, "grad_B_per_particle": 2.0, "compile_s": 1.0}  # fmt: skip
    monkeypatch.setattr(mpm, "run_config", lambda cfg, interp=None: dict(row))
    out = tmp_path / "bench"
    assert run_bench("mpm", out, quick=True) == 0
    line = "guards off: CFL, NaN, domain, energy budget (the MPM engine timed alone at a fixed dt = 1e-4 s)"
    assert _guard_lines(capsys.readouterr().out) == [line]
    assert _guard_lines((out / "mpm.md").read_text()) == [f"- {line}"]
    assert {r["guards_off"] for r in csv.DictReader((out / "mpm.csv").open())} == {"CFL; NaN; domain; energy budget"}


def test_measure_only_records_the_energy_excess_without_stopping():
    """Energy from nowhere (tripled velocities) stops a run; after ``measure_only`` the same step runs and
    records the excess (what `cosim bench contact` reports)."""
    scene = make_scene(steps=3)

    def tripled(sim):
        sim.step()
        state = dict(sim.mpm.state())
        state["v"] = state["v"] * 0.0 + 3.0
        sim.mpm.set_state(state)
        sim.step()
        return sim

    with pytest.raises(SimulationError, match="the energy grew"):
        tripled(build_system(scene))
    sim = build_system(scene)
    measure_only(sim)
    assert tripled(sim).conservation.excess > 1.0 and math.isinf(sim.tunnel_share)
