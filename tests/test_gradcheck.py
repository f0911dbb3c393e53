"""`check_gradients` judges each direction on |adjoint - difference| against the larger of the two and
the difference's measured noise floor: a wrong or missing tiny gradient fails, a right one passes, and a
difference that is round-off alone passes labelled (NumPy losses: no simulation)."""

from __future__ import annotations

import numpy as np
import pytest

from cosim.adjoint.gradcheck import ULP, check_gradients, relative_error, report_gradcheck
from cosim.errors import GradientCheckError

W = np.random.default_rng(0).standard_normal(6)
TINY = 1e-10  # the loss's variation, relative to its value 1: below the old 1e-6 |L| floor


def objective(loss, gradient):
    """``evaluate(params, grad)`` of a NumPy loss of one parameter ``x`` and a claimed gradient."""

    def evaluate(params, grad):
        x = params["x"]
        return loss(x), ({"x": gradient(x)} if grad else None)

    return evaluate


def tiny(x):
    return 1.0 + TINY * (W @ x + 0.5 * x @ x)


def tiny_gradient(x):
    return TINY * (W + x)


def check(gradient, loss=tiny, x=None):
    x = np.random.default_rng(1).standard_normal(6) * 0.1 if x is None else x
    return check_gradients(objective(loss, gradient), {"x": x}, ["x"], {"x": 1.0}, directions=3)


@pytest.mark.parametrize(
    "gradient", [lambda x: 2.0 * tiny_gradient(x), lambda x: np.zeros_like(x)], ids=["twice", "zero"]
)
def test_a_wrong_or_missing_tiny_gradient_fails(gradient):
    for r in check(gradient):
        assert r.verdict(1e-4) == "fail", r
        assert r.relative_error == pytest.approx(0.5 if r.adjoint else 1.0, abs=0.05)
        assert abs(r.finite_difference) > 5 * r.noise_floor  # resolved: above the floor


def test_a_right_tiny_gradient_passes():
    results = check(tiny_gradient)
    assert all(r.passed(1e-4) for r in results), results
    assert all(r.relative_error < 0.1 for r in results)  # the loss's round-off, over a 1e-10 variation


def test_a_round_off_difference_with_zero_adjoint_passes_labelled(capsys):
    """A loss that jitters by one ulp (round-off) and has no gradient: the difference is not 0, it is
    below its noise floor, so the direction passes, with an error below 1 and a label that says why."""

    def jitter(x):
        return 1.0 + ULP * (round(1e5 * float(W @ x)) % 2)

    results = check(lambda x: np.zeros_like(x), loss=jitter)
    rough = [r for r in results if r.finite_difference != 0]
    assert rough, results  # the case is exercised
    for r in rough:
        assert 0 < r.relative_error < 1 and r.verdict(1e-4) == "noise", r
    assert report_gradcheck(results, 1e-4, 3) == 0
    out = capsys.readouterr().out
    assert "within the noise floor: unresolved, passes" in out and "noise floor" in out.splitlines()[0]


def test_both_zero_is_error_zero_and_a_nonzero_gap_never_is():
    assert relative_error(0.0, 0.0, 0.0) == 0.0
    assert relative_error(0.0, 1e-30, 1e-12) > 0  # below the floor: small, not 0
    assert relative_error(0.0, 3e-3, 1e-12) == 1.0


def test_the_report_fails_a_resolved_disagreement(capsys):
    with pytest.raises(GradientCheckError, match="above their noise floor"):
        report_gradcheck(check(lambda x: 2.0 * tiny_gradient(x)), 1e-4, 3)
    assert "max relative error: 5" in capsys.readouterr().out


def test_a_one_entry_parameter_is_checked_along_its_one_direction():
    """A parameter of one entry has one direction up to sign: three would run the same rollouts three times.
    A six-entry parameter still gets its three; each resolved direction costs two rollouts after the gradient's."""
    calls = []

    def evaluate(params, grad):
        calls.append(grad)
        loss = 1.0 + W @ params["x"] + 3.0 * params["E"][0]
        return loss, ({"x": W.copy(), "E": np.array([3.0])} if grad else None)

    params = {"x": np.zeros(6), "E": np.array([1.0])}
    results = check_gradients(evaluate, params, ["x", "E"], {"x": 1.0, "E": 1.0}, directions=3)
    assert [r.param for r in results] == ["x", "x", "x", "E"]
    assert all(r.relative_error < 1e-8 for r in results), results
    assert calls == [True] + [False] * 8
