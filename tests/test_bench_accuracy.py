"""`cosim bench accuracy`'s machinery: the Pareto front, the error measures on cases with known
answers, the report, and one simulated case against its closed form."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from cosim.bench import accuracy_measures as am
from cosim.bench import work_precision as wp
from cosim.bench.accuracy import Case, sweep_cases
from cosim.bench.accuracy_problem import Setting
from cosim.bench.accuracy_problems import PROBLEMS

# (cost, error): 5 = (0.5, 0.9), 0 = (1, 0.5), 1 = (2, 0.2), 4 = (4, 0.1) are on the front; 2 and 3 are
# beaten by 1, 6 by 4 (same error, costlier), 7 has no error
COSTS = [1.0, 2.0, 2.0, 3.0, 4.0, 0.5, 5.0, 0.1]
ERRORS = [0.5, 0.2, 0.3, 0.25, 0.1, 0.9, 0.1, math.nan]


def test_pareto_front_of_a_hand_made_set():
    assert wp.pareto_front(COSTS, ERRORS) == [5, 0, 1, 4]
    assert wp.pareto_front([1.0, 1.0], [0.2, 0.2]) == [0]  # of duplicates, the first


def test_where_a_point_sits_against_the_front():
    assert wp.cheapest_within(COSTS, ERRORS, 0.25) == 1
    assert wp.cheapest_within(COSTS, ERRORS, 0.05) is None
    assert wp.best_within(COSTS, ERRORS, 3.5) == 1
    pos = wp.default_position([{"cost": c, "error": e} for c, e in zip(COSTS, ERRORS)], [5, 0, 1, 4], 3)
    assert not pos["on_front"]
    assert pos["cheaper"] == 1 and pos["speedup"] == pytest.approx(1.5)  # error 0.2 <= 0.25 at 2/3 the cost
    assert pos["better"] == 1 and pos["error_ratio"] == pytest.approx(1.25)
    rows = [{"cost": c, "error": e} for c, e in zip(COSTS, ERRORS)]
    tied = wp.default_position(rows, [5, 0, 1, 4], 3, cost_tie=1.6, error_tie=1.3)  # 1.5x cheaper, 1.25x smaller
    assert tied["cheaper"] == tied["better"] == 3


def test_period_of_a_synthetic_signal_with_odd_harmonics():
    """Odd harmonics of one period cross zero exactly every half period; sampled off-grid at 1/60 of
    the period, linear interpolation between samples is exact to O(dt^3) there (the curvature vanishes)."""
    T = 0.1197
    t = np.arange(0.0, 2.25 * T, T / 60.3)
    s = np.sin(2 * np.pi * t / T) + 0.2 * np.sin(6 * np.pi * t / T) - 0.05 * np.sin(10 * np.pi * t / T)
    assert am.oscillation_period(t, s) == pytest.approx(T, rel=1e-5)
    assert math.isnan(am.oscillation_period(t[:20], s[:20]))  # one crossing: no period


def test_bar_closed_form():
    """nu = 0: no lateral contraction, omega = (pi / L) sqrt(E / rho); nu > 0: the plane-strain modulus
    E / (1 - nu^2) raises it, lateral inertia lowers it, more for a wider strip. The gradient formula
    against a central difference of q(t; E) = (v0 / omega(E)) sin(omega(E) t)."""
    assert am.bar_angular_frequency(0.5, 0.1, 1e5, 0.0, 1000.0) == pytest.approx(np.pi / 0.5 * 10.0)
    thin = am.bar_angular_frequency(0.5, 1e-6, 1e5, 0.3, 1000.0)
    assert thin == pytest.approx(np.pi / 0.5 * np.sqrt(1e5 / 0.91 / 1000.0))
    assert am.bar_angular_frequency(0.5, 0.2, 1e5, 0.3, 1000.0) < thin

    def q(E: float, t: float) -> float:
        w = am.bar_angular_frequency(0.625, 0.125, E, 0.3, 1000.0)
        return 0.05 / w * np.sin(w * t)

    E, t, eps = 1e5, 0.13, 1e-6
    numeric = (q(E * np.exp(eps), t) - q(E * np.exp(-eps), t)) / (2 * eps)
    omega = am.bar_angular_frequency(0.625, 0.125, E, 0.3, 1000.0)
    assert am.bar_modal_gradient(0.05, omega, t) == pytest.approx(numeric, rel=1e-7)


def test_resting_height_against_the_integrated_column():
    """The self-weight drop rho g H^2 / (3 E') is the mean over the block of u(y) = -int_0^y eps,
    eps(y) = rho g (H - y) / E' (uniaxial stress, free sides)."""
    H, E, nu, rho, g = 0.2, 5e4, 0.3, 1000.0, 9.81
    y = (np.arange(20000) + 0.5) * H / 20000
    eps = rho * g * (H - y) / (E / (1 - nu**2))
    u = -(np.cumsum(eps) - 0.5 * eps) * (H / 20000)  # the integral up to each cell's middle
    assert am.resting_com_height(0.3, H, E, nu, rho, g) == pytest.approx(0.3 + np.mean(y + u), abs=1e-8)


def test_buoyancy_measure_on_an_exact_floating_box():
    """Water particles on a lattice of spacing h up to a surface at 0.25 m, a box of height 0.1 whose
    bottom is 0.04 below the surface, water only beside and below it: the measured fraction is 0.4."""
    h, surface, box_y, height = 1 / 128, 0.25, 0.25 - 0.04 + 0.05, 0.1
    xs = np.arange(0.1 + h / 2, 0.9, h)
    ys = np.arange(0.0625 + h / 2, surface, h)  # 24 layers
    x = np.stack(np.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)
    under_box = (np.abs(x[:, 0] - 0.5) < 0.15) & (x[:, 1] > box_y - height / 2)
    x = x[~under_box]
    level = am.surface_level(x, h, 0.5, 0.18)
    assert level == pytest.approx(surface, abs=1e-12)
    assert am.submerged_fraction(level, box_y, height) == pytest.approx(0.4, abs=1e-10)
    assert am.effective_height(ys, h) == pytest.approx(surface - 0.0625)  # a lattice column's height


def test_quick_sweep_has_one_case_per_problem_and_references_at_twice_its_grid():
    cases = sweep_cases(PROBLEMS, quick=True)
    plain = [c for c in cases if not c.reference]
    assert sorted(c.problem for c in plain) == sorted(PROBLEMS)
    for c in cases:
        if c.reference:
            assert c.setting.cells == 2 * PROBLEMS[c.problem].cells[0] and c.setting.precision == "float64"
    full = sweep_cases(PROBLEMS)
    assert len(set(full)) == len(full)
    assert all(any(c.setting == p.default for c in full if c.problem == n) for n, p in PROBLEMS.items())


def test_the_report_from_made_up_observations(tmp_path):
    """The bar's error is read against its closed form; two settings, the cheaper one less accurate."""
    from cosim.bench.accuracy_report import Measurement, write_report

    bar = PROBLEMS["elastic_bar"]
    exact = 2 * np.pi / bar.omega
    cases = [Case("elastic_bar", Setting(32, 0.3, "float32")), Case("elastic_bar", bar.default)]
    results = [
        {"period": exact * 1.02, "seconds": 1.5, "cpu_seconds": 1.0, "sim_seconds": 0.5, "cost": 2.0},
        {"period": exact * 0.995, "seconds": 5.0, "cpu_seconds": 4.0, "sim_seconds": 0.5, "cost": 8.0},
    ]
    measurement = Measurement("a CPU, 2 cores", "2026-12-02T12:00", (1.0, 2.0, 3.0), (1.5, 2.0, 3.0), "test")
    failed = write_report(tmp_path, {"elastic_bar": bar}, cases, results, measurement, quick=False)
    assert failed == 0
    text = (tmp_path / "accuracy.csv").read_text()
    assert text.startswith("# hardware: a CPU, 2 cores\n")
    assert "1.00 / 2.00 / 3.00 at the start" in text
    rows = list(csv.DictReader(line for line in text.splitlines() if not line.startswith("#")))
    assert [float(r["error"]) for r in rows] == pytest.approx([0.02, 0.005])
    assert [r["on_front"] for r in rows] == ["True", "True"]
    assert (tmp_path / "accuracy_elastic_bar.png").stat().st_size > 0
    md = (tmp_path / "accuracy.md").read_text()
    assert "| elastic_bar | 64 cells/m, cfl 0.3, float32 | 0.005 | 8 | yes |" in md


def test_coarsest_bar_vibrates_at_the_closed_form_period():
    """The quick case of elastic_bar (32 cells/m: 4 cells across the strip), here in float64: its
    period within 1% of the plane-strain Rayleigh-Love bar's (measured 0.35%; the
    lateral-inertia term alone is 0.3%, so the bound also fails without it at finer grids), and the
    error shrinks at 64 cells/m (measured 0.12%)."""
    bar = PROBLEMS["elastic_bar"]
    coarse = bar.error(bar.run(Setting(32, 0.3, "float64")), None)
    fine = bar.error(bar.run(Setting(64, 0.3, "float64")), None)
    assert coarse < 0.01
    assert fine < coarse
