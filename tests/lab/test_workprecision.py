"""Standard problems and the work–precision sweep at small sizes."""

import json
import re

import numpy as np
import pytest

from prdp_petsc.lab.reports import problems, workprecision


@pytest.mark.parametrize("name", sorted(problems.PROBLEMS))
def test_problem_gradient_matches_finite_differences(name):
    p = problems.build_problem(name, quick=True)
    A = p.matrix()
    assert p.symmetric == (abs(A - A.T).max() <= 1e-14 * abs(A).max())
    x, _, grad = problems.direct_gradient(p)
    assert p.loss(x) > 0
    h = p.theta * np.random.default_rng(0).uniform(-1, 1, p.theta.size)
    eps = 1e-6
    from scipy.sparse.linalg import spsolve

    def J(t):
        return p.loss(spsolve(p.matrix(t).tocsc(), p.b))

    fd = (J(p.theta + eps * h) - J(p.theta - eps * h)) / (2 * eps)
    assert fd == pytest.approx(grad @ h, rel=1e-6)


def test_pairs_apply_to_the_operator():
    sym = workprecision.pairs_for(True)
    non = workprecision.pairs_for(False)
    assert ("cg", "icc") in sym and ("richardson", "gamg") in sym and len(sym) == 20
    assert not any(k == "cg" or p == "icc" for k, p in non)
    assert ("gmres", "ilu") in non


def test_work_precision_main(tmp_path):
    """Relations of the sweep (counts and errors, never times), poisson quick, K = 1 … 32.

    Measured: forward error at K = 8 is 1.2e-8 (CG + GAMG), 0.13 (SOR), 0.33 (Jacobi),
    0.97 (damped Richardson + Jacobi, contracting by 0.99674 and 0.99677 per iteration
    over K = 8 → 16 and 16 → 32).  The summary's cheapest point per level is picked by
    wall time, so it is not asserted.
    """
    pairs = ["cg/gamg", "cg/sor", "cg/jacobi", "richardson/jacobi"]
    routes = ",".join(pairs)
    argv = ["poisson", "--preset", "quick", "--out", str(tmp_path), "--k-max", "32"]
    argv += ["--routes", routes]
    assert workprecision.main(argv) == 0
    data = json.loads((tmp_path / "work_precision_poisson.json").read_text())
    assert (tmp_path / "work_precision_poisson.png").stat().st_size > 10_000
    table = (tmp_path / "work_precision_poisson.md").read_text()
    assert "| cg/gamg |" in re.sub(r" +", " ", table) and "gradient error ≤ 1e-02" in table

    def points(pair):
        return [r for r in data["rows"] if r["pair"] == pair]

    # fixed mode: exactly K iterations forward and K in the adjoint, every point
    assert all(r["iterations"] == r["K"] == r["adjoint_iterations"] for r in data["rows"])
    forward = {p: {r["K"]: r["forward_error"] for r in points(p)} for p in pairs}
    for pair in pairs:  # the forward error falls with every doubling of K ...
        errors = list(forward[pair].values())
        assert all(b < a for a, b in zip(errors, errors[1:])), pair
        gradient = [r["gradient_error"] for r in points(pair)]
        assert gradient[-1] < gradient[0], pair  # ... and so, in the end, does the gradient's
    # ... and at equal K a stronger preconditioner leaves less: GAMG < SOR < Jacobi
    for k, gamg in forward["cg/gamg"].items():
        assert gamg < forward["cg/sor"][k] < forward["cg/jacobi"][k], k
    gamg = points("cg/gamg")
    assert gamg[-1]["gradient_error"] <= 1e-8
    assert gamg[-1]["gradient_cosine"] == pytest.approx(1.0, abs=1e-12)
    # GAMG: K-independent contraction, so each doubling of K from 2 on at least squares
    # the gain: gradient error 3.5e-2, 5.8e-4, 1.1e-7, 2.0e-14 at K = 2, 4, 8, 16
    grad = {r["K"]: r["gradient_error"] for r in gamg}
    assert all(grad[2 * k] < grad[k] ** 1.5 for k in (2, 4, 8))
    # damped Richardson contracts geometrically: the same rate over 8 → 16 and 16 → 32
    rich = forward["richardson/jacobi"]
    rates = [(rich[2 * k] / rich[k]) ** (1 / k) for k in (8, 16)]
    assert rates[0] < 1 and rates[1] == pytest.approx(rates[0], abs=1e-3)
