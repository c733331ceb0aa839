"""Rows of the stability suite: evaluate one case (solve through the bridge, residual,
iterations, Taylor rate of the gradient, NaN/Inf, or the error a failing case must
raise) and format the rows as a Markdown table.

Used by `prdp_petsc.lab.reports.stability`, which defines the cases.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from .kinds import markdown_table

__all__ = ["CONVERGED", "centroids", "evaluate", "poisson_problem", "taylor_rate", "to_markdown"]

logger = logging.getLogger(__name__)

#: converged settings of the reference solves
CONVERGED = {"max_it": 2000, "rtol": 1e-12}


# -- building blocks -----------------------------------------------------------------------
def taylor_rate(J, theta: np.ndarray, dJ: np.ndarray, h: np.ndarray, *, points: int = 5):
    """Rate of the Taylor remainder ``|J(θ + εh) − J(θ) − ε ⟨dJ, h⟩|`` (2: gradient right).

    ε runs over 0.5 · 2⁻ᵏ, k = 0 … 9.  The evaluation noise of J is measured at
    ε = ±1e-8, where the true remainder is negligible; only remainders above 30 ×
    that noise are used, and of those the `points` smallest ε (the most asymptotic).
    The rate is the least-squares slope of log remainder against log ε.

    Returns
    -------
    rate : float
        NaN when fewer than three remainders lie above the noise.
    info : dict
        ``eps`` and ``remainders`` used, and the ``noise`` level.
    """
    j0 = J(theta)
    slope = float(np.dot(dJ, h))
    noise = max(abs(J(theta + d * h) - j0 - d * slope) for d in (1e-8, -1e-8))
    eps = 0.5 * 0.5 ** np.arange(10)
    rem = np.array([abs(J(theta + e * h) - j0 - e * slope) for e in eps])
    keep = np.flatnonzero(np.isfinite(rem) & (rem > 30 * noise))[-points:]
    info = {"eps": eps[keep].tolist(), "remainders": rem[keep].tolist(), "noise": noise}
    if keep.size < 3:
        return float("nan"), info
    return float(np.polyfit(np.log(eps[keep]), np.log(rem[keep]), 1)[0]), info


def poisson_problem(mesh, *, dirichlet: bool = True, form=None, coefficient_basis=None):
    """(A(θ) on the unknowns, load vector of f = 1, basis) for −∇·(κ∇u) = 1."""
    from skfem import Basis, ElementTriP0, ElementTriP1, LinearForm

    from prdp_petsc import Dirichlet, diffusion_operator, from_form

    basis = Basis(mesh, ElementTriP1())
    if form is None:
        A = diffusion_operator(basis)
    else:
        A = from_form(form, basis, basis.with_element(ElementTriP0()), positive=True)

    @LinearForm
    def one(v, w):
        return 1.0 * v

    b = one.assemble(basis)
    if not dirichlet:
        return A, b, basis
    d = Dirichlet(A, basis.get_dofs())
    return d.A_II, b[d.interior], basis


def centroids(mesh) -> np.ndarray:
    return mesh.p[:, mesh.t].mean(axis=1)


def _options_label(options: str) -> str:
    parts = options.split()
    kv = dict(zip(parts[::2], parts[1::2], strict=False))
    return f"{kv.get('-ksp_type', '?')}/{kv.get('-pc_type', '?')}"


def evaluate(
    case: str,
    setting: str,
    A,
    theta: np.ndarray,
    b: np.ndarray,
    options: str,
    *,
    max_it: int = CONVERGED["max_it"],
    rtol: float = CONVERGED["rtol"],
    adjoint=None,
    nullspace=None,
    taylor: bool = True,
    seed: int = 0,
    note: str = "",
) -> dict:
    """Solve, differentiate and Taylor-test one configuration; return a table row.

    ``J(θ) = ⟨w, x(θ)⟩`` with w random of zero mean; the Taylor direction is
    ``h = θ ⊙ r``, r uniform in [−1, 1].  Errors of the library (`SolverError`,
    `ValueError`) become the row's outcome.
    """
    import torch

    from prdp_petsc import KSPSolver, SolverError, Structure, solve

    rng = np.random.default_rng(seed)
    n = A.shape[0]
    w = rng.standard_normal(n)
    w -= w.mean()  # J does not see the constant mode (see the module docstring)
    h = theta * rng.uniform(-1.0, 1.0, theta.size)
    row = {
        "case": case,
        "setting": setting,
        "solver": _options_label(options),
        "n": int(n),
        "iterations": None,
        "adjoint_iterations": None,
        "reason": None,
        "residual": None,
        "taylor_rate": None,
        "nan_or_inf": False,
        "outcome": "ok",
        "note": note,
    }
    solver = KSPSolver(
        options,
        max_it=max_it,
        rtol=rtol,
        adjoint=adjoint,
        structure=Structure(nullspace=nullspace),
        not_converged="ignore",  # each row records its own outcome
    )
    b_t = torch.from_numpy(np.asarray(b, dtype=np.float64))
    w_t = torch.from_numpy(w)
    t0 = time.perf_counter()
    try:
        th = torch.tensor(theta, dtype=torch.float64, requires_grad=True)
        sol = solve(A, b_t, solver, theta=th, return_solution=True)
        x = sol.value
        row["iterations"] = sol.iterations
        row["reason"] = sol.reason
        xn = x.detach().numpy()
        scale = float(np.max(np.abs(b)))  # |b| may be 1e-300: norms would underflow
        r = (b - A.matrix(theta) @ xn) / scale
        bb = np.asarray(b, dtype=np.float64) / scale
        if nullspace is not None:  # residual of the projected (compatible) problem
            r, bb = r - r.mean(), bb - bb.mean()
        row["residual"] = float(np.linalg.norm(r) / np.linalg.norm(bb))
        J = (w_t * x).sum()
        J.backward()
        grad = th.grad.numpy()
        row["adjoint_iterations"] = solver.stats.adjoint_iterations
        row["nan_or_inf"] = bool(not (np.all(np.isfinite(xn)) and np.all(np.isfinite(grad))))
        if taylor:

            def functional(t):
                with torch.no_grad():
                    xt = solve(A, b_t, solver, theta=torch.from_numpy(t))
                return float((w_t * xt).sum())

            row["taylor_rate"], taylor = taylor_rate(functional, theta, grad, h)
            row["taylor_eps"] = [min(taylor["eps"], default=None), max(taylor["eps"], default=None)]
            row["taylor_noise"] = taylor["noise"] / max(abs(float(J.detach())), 1e-300)
        row["_x"], row["_grad"] = xn, grad
    except (SolverError, ValueError) as err:
        if isinstance(err, SolverError) and row["reason"] is None:
            row["reason"] = err.reason  # the failing solve's PETSc reason
        row["outcome"] = f"{type(err).__name__}: {getattr(err, 'reason', '') or str(err)[:60]}"
        row["message"] = str(err)
    row["seconds"] = time.perf_counter() - t0
    return row


# -- cases ----------------------------------------------------------------------------------


def _fmt(value, spec: str) -> str:
    if value is None or (isinstance(value, float) and np.isnan(value)):
        return "—"
    return format(value, spec)


def _eps_range(row: dict) -> str:
    lo, hi = row.get("taylor_eps") or (None, None)
    return "—" if lo is None else f"{lo:.0e}–{hi:.0e}"


def to_markdown(rows: list[dict]) -> str:
    """The rows as a markdown table."""
    header = ["case", "setting", "KSP/PC", "n", "its fwd/adj", "reason", "‖b−Ax‖/‖b‖"]
    header += ["Taylor rate", "Taylor ε", "NaN/Inf", "outcome"]
    cells = []
    for r in rows:
        its = "—"
        if r["iterations"] is not None:
            its = f"{r['iterations']}/{_fmt(r['adjoint_iterations'], 'd')}"
        outcome = r["outcome"] + (f"; {r['note']}" if r.get("note") else "")
        lo = (r.get("taylor_eps") or [None])[0]
        if lo is not None and lo > 2e-3:  # the smallest ε were below J's rounding noise
            outcome += f"; J rounding noise {r['taylor_noise']:.0e} (relative): ε ≥ {lo:.0e}"
        if "projection_error" in r:
            outcome += f" (vs compatible: {r['projection_error']:.1e})"
        cells.append((r["case"], r["setting"], r["solver"], r["n"], its, r["reason"] or "—",
                      _fmt(r["residual"], ".1e"), _fmt(r["taylor_rate"], ".2f"), _eps_range(r),
                      "yes" if r["nan_or_inf"] else "no", outcome))  # fmt: skip
    return markdown_table(header, cells, "lllrrlrrlll") + "\n"
