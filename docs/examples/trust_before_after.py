"""Nine paths that once returned a wrong number silently, run against any version.

Uses only API that existed before the library refused them, so the same script shows
the old behaviour and the new one::

    git worktree add /tmp/base 10845e6        # the release before
    REPO=/tmp/base PYTHONPATH=/tmp/base python docs/examples/trust_before_after.py
    REPO=. python docs/examples/trust_before_after.py

Each line prints what the call returned or raised.
"""

import os
import pathlib
import subprocess
import sys
import tempfile

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

import prdp_petsc as pp


def solved(s, rhs):
    """x and its `SolveInfo`: today a `LinearSolution` carries both; the release before
    returned the array and kept the outcome on the solver (``s.last``)."""
    out = s.solve(rhs)
    if isinstance(out, np.ndarray):
        return out, s.last
    return out.value, out.info[-1]


def outcome(f):
    try:
        return "returned: " + str(f())
    except SystemExit as e:
        return f"SystemExit({e.code})"
    except BaseException as e:
        return f"raised {type(e).__name__}: {str(e)[:90]}"


n = 60
h = 1 / (n + 1)
adv = sp.diags(
    [-np.ones(n - 1) / h**2 - 20 / h, 2 * np.ones(n) / h**2, -np.ones(n - 1) / h**2 + 20 / h],
    [-1, 0, 1],
).tocsr()
rhs = np.random.default_rng(0).standard_normal(n)
exact = spla.spsolve(adv.tocsc(), rhs)


def one():
    out = []
    for o in ("-ksp_type cg -pc_type jacobi", "-ksp_type minres", "-ksp_type cg -pc_type icc"):
        s = pp.KSPSolver(o, max_it=40)
        s.set_operator(adv)
        x, info = solved(s, rhs)
        err = np.linalg.norm(x - exact) / np.linalg.norm(exact)
        out.append(f"{o.split()[1]}/{o.split()[-1]}: rel.err {err:.2f} {info.reason}")
    return "; ".join(out)


def two():
    M = adv.copy()
    M0 = M.copy()
    g = np.ones(n)
    s = pp.KSPSolver("-ksp_type gmres -pc_type ilu", max_it=300, rtol=1e-13)
    b = torch.tensor(rhs, requires_grad=True)
    x = pp.solve(M, b, s)
    M.data *= 3
    pp.solve(M, torch.tensor(rhs), s)
    x.backward(torch.tensor(g))
    ref = spla.spsolve(M0.T.tocsc(), g)
    return f"gradient rel.err {np.linalg.norm(b.grad.numpy() - ref) / np.linalg.norm(ref):.2f}"


def three_a():
    s = pp.KSPSolver("-ksp_type cg", max_it=10)
    s.set_operator(adv + adv.T)
    bad = rhs.copy()
    bad[3] = np.nan
    x, info = solved(s, bad)
    return f"x max |.| = {np.abs(x).max()}, reason = {info.reason}"


def three_b():
    A = (adv + adv.T).tocsr()
    s = pp.KSPSolver("-ksp_type cg", max_it=10)
    b = torch.tensor(rhs, requires_grad=True)
    x = pp.solve(A, b, s)
    g = torch.zeros(n, dtype=torch.float64)
    g[7] = torch.nan
    x.backward(g)
    return f"grad max |.| = {b.grad.abs().max().item()}"


def four():
    import skfem
    from skfem import BilinearForm
    from skfem.helpers import dot, grad

    basis = skfem.Basis(skfem.MeshTri().refined(3), skfem.ElementTriP1())
    cb = basis.with_element(skfem.ElementTriP0())

    @BilinearForm
    def form(u, v, w):
        return w.kappa * dot(grad(u), grad(v)) + u * v

    A = pp.from_form(form, basis, cb)
    th = 1 + np.random.default_rng(0).random(A.n_params)
    direct = form.assemble(basis, kappa=cb.interpolate(th))
    diff = abs(A.matrix(th) - direct).max() / abs(direct).max()
    return f"max entry error / max entry = {diff:.1e}"


def five():
    s = pp.KSPSolver("-ksp_type richardson -pc_type sor", max_it=3)
    s.set_operator(adv + adv.T)
    x, info = solved(s, rhs)
    r = np.linalg.norm(rhs - (adv + adv.T) @ x) / np.linalg.norm(rhs)
    return f"{info}, converged={info.converged}, true rel. residual {r:.2f}"


def six():
    d = tempfile.mkdtemp()
    p = pathlib.Path(d) / "bad.msh"
    p.write_text("hello")
    return pp.load_mesh(str(p))


def eight():
    scene = """
import numpy as np, scipy.sparse as sp, torch
import prdp_petsc as pp
from prdp_petsc import lab
PRESETS = {"quick": {}, "paper": {}}
def build(config, seed):
    A = (sp.identity(10) - 1e-2 * laplacian(10)).tocsr()
    s = pp.KSPSolver({"ksp_type": "richardson", "pc_type": "jacobi"}, prefix="t_", max_it=1)
    th = torch.ones(10, dtype=torch.float64, requires_grad=True)
    def loss(_):
        np.ones(3) + np.ones(4)  # a bug in the scene
    return lab.Scene(solvers=[s], optimizer=torch.optim.SGD([th], lr=0.1), batches=lambda e, g: [0],
                    loss=loss, validate=lambda: 1.0, probe=lambda: (A, np.ones(10)), epochs=2)
"""
    d = tempfile.mkdtemp()
    p = pathlib.Path(d) / "buggy.py"
    p.write_text(scene)
    from prdp_petsc.lab.training.harness import run

    r = run(p, "fixed:1", epochs=2, progress=False)
    return f"stopped = {r['stopped']}"


def nine():
    r = subprocess.run(
        [
            sys.executable,
            "-W",
            "error::prdp_petsc.errors.UnusedOptionWarning",
            "-m",
            "prdp_petsc.lab.cli",
            "run",
            "demos/poisson_inverse.py",
            "--preset",
            "quick",
            "--epochs",
            "1",
            "--no-progress",
            "--out",
            tempfile.mkdtemp(),
            "-poisson_ksp_tpye",
            "cg",
        ],
        capture_output=True,
        text=True,
        cwd=os.environ.get("REPO", "."),
    )
    last = r.stderr.strip().splitlines()[-1][:100] if r.stderr.strip() else ""
    return f"exit {r.returncode}; stderr: {last}"


for name, f in [
    ("1 CG/MINRES/ICC on advection", one),
    ("2 operator edited in place", two),
    ("3a NaN rhs", three_a),
    ("3b NaN cotangent", three_b),
    ("4 non-affine form", four),
    ("5 Richardson+SOR K=3", five),
    ("6 unparsable mesh", six),
    ("8 bug in a scene", eight),
    ("9 -W error::...UnusedOptionWarning", nine),
]:
    print(f"{name}: {outcome(f)}", flush=True)
