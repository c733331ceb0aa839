"""Standard problems and the work–precision sweep at small sizes."""

import json

import numpy as np
import pytest

from prdp_petsc.reports import problems, workprecision


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
    argv = ["poisson", "--quick", "--out", str(tmp_path), "--kmax", "32"]
    argv += ["--pairs", "cg/gamg", "cg/sor", "richardson/jacobi"]
    assert workprecision.main(argv) == 0
    data = json.loads((tmp_path / "work_precision_poisson.json").read_text())
    assert (tmp_path / "work_precision_poisson.png").stat().st_size > 10_000
    table = (tmp_path / "work_precision_poisson.md").read_text()
    assert "| cg/gamg |" in table and "gradient error ≤ 1e-02" in table

    def points(pair):
        return [r for r in data["rows"] if r["pair"] == pair]

    gamg = points("cg/gamg")
    errors = [r["gradient_error"] for r in gamg]
    assert errors[-1] <= 1e-8 and errors[-1] < errors[0]
    assert gamg[-1]["gradient_cosine"] == pytest.approx(1.0, abs=1e-12)
    assert all(r["iterations"] == r["K"] == r["adjoint_iterations"] for r in gamg)
    # the SOR adjoint runs on an explicit transpose and is as accurate
    assert points("cg/sor")[-1]["forward_error"] <= 1e-3
    # damped Jacobi converges, slowly and monotonically in the forward error
    rich = [r["forward_error"] for r in points("richardson/jacobi")]
    assert len(rich) == 6 and all(b < a for a, b in zip(rich, rich[1:]))
    assert all(r["t_total"] > 0 for r in data["rows"])
