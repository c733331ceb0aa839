"""Stability suite: hard linear problems through capped PETSc solves and their gradients.

Each row solves ``A(θ) x = b`` through the torch bridge (`prdp_petsc.solve`) and
reports the forward residual ``‖b − A x‖/‖b‖``, the forward and adjoint iterations,
the Taylor rate of the gradient of ``J(θ) = ⟨w, x(θ)⟩`` (2 when the gradient is right,
1 when it is inconsistent) and whether anything became NaN/Inf; a case that must fail
reports the error type and PETSc reason.  Cases:

* stiff heat steps ``(M + Δt K(κ)) u¹ = M u⁰``, Δt κ / h² from 1e-2 to 1e8;
* coefficient contrast up to 1e8 (disc inclusions, checkerboard);
* rotated anisotropy up to 1e4;
* pure Neumann Poisson (constant null space; compatible and incompatible rhs);
* the ``sliver`` mesh (minimum angle 1.8°);
* K = 1, and K far beyond convergence with ``rtol = atol = 0``;
* right-hand sides of size 1e-150, 1e150 (and 1e-300);
* an adjoint PC without a transpose, a KSP without a correct transpose solve, real
  breakdowns (BiCGStab on a skew operator, CG on an indefinite one).

The functional's weight w has zero mean.  In the stiff heat step at Δt κ/h² = 1e8
the solution is its (θ-independent, conserved) mean plus a θ-dependent part 1e-8
times smaller; rounding in the mean, which any float64 solver (also LU) makes at
cond·eps ≈ 1e-8, would swamp a J that sees the mean.

Run ``prdp-petsc stability --out DIR`` (``--preset quick`` for small meshes); it writes
``DIR/stability.json`` and ``DIR/stability.md``.
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np
import scipy.sparse as sp

from ..provenance import write_result
from .kinds import DataSet, ReportKind, markdown_table
from .problems import poisson_problem

__all__ = ["CASES", "KIND", "TAYLOR_RIGHT", "evaluate", "main", "run_cases", "summary_counts",
           "summary_line", "taylor_rate", "to_markdown"]  # fmt: skip

logger = logging.getLogger(__name__)

#: converged settings of the reference solves
CONVERGED = {"max_it": 2000, "rtol": 1e-12}
#: a Taylor rate at or above this says the gradient is right (2 in exact arithmetic)
TAYLOR_RIGHT = 1.85

GAMG, ICC, JACOBI = (f"-ksp_type cg -pc_type {pc}" for pc in ("gamg", "icc", "jacobi"))


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


def centroids(mesh) -> np.ndarray:
    return mesh.p[:, mesh.t].mean(axis=1)


def _mesh(name: str, quick: bool, full: int = 1):
    from prdp_petsc import load_mesh

    return load_mesh(name, 0 if quick else full)


def _lshape_poisson(quick: bool):
    mesh = _mesh("lshape", quick)
    A, b, _ = poisson_problem(mesh)
    return A, b, np.ones(mesh.t.shape[1])


def evaluate(case: str, setting: str, A, theta, b, options: str, *, nullspace=None,
             taylor: bool = True, note: str = "", **settings) -> dict:  # fmt: skip
    """Solve, differentiate and Taylor-test one configuration; return a table row.

    The solver is `KSPSolver` with `options` and `settings` (``max_it``, ``rtol``,
    ``adjoint``; `CONVERGED` by default).  ``J(θ) = ⟨w, x(θ)⟩`` with w random of zero
    mean; the Taylor direction is ``h = θ ⊙ r``, r uniform in [−1, 1].  Errors of the
    library (`SolverError`, `ValueError`) become the row's outcome.
    """
    import torch

    from prdp_petsc import KSPSolver, SolverError, Structure, solve

    rng = np.random.default_rng(0)
    n = A.shape[0]
    w = rng.standard_normal(n)
    w -= w.mean()  # J does not see the constant mode (see the module docstring)
    h = theta * rng.uniform(-1.0, 1.0, theta.size)
    words = options.split()
    kv = dict(zip(words[::2], words[1::2], strict=False))
    row = {"case": case, "setting": setting,
           "solver": f"{kv.get('-ksp_type', '?')}/{kv.get('-pc_type', '?')}", "n": int(n),
           "iterations": None, "adjoint_iterations": None, "reason": None, "residual": None,
           "taylor_rate": None, "nan_or_inf": False, "outcome": "ok", "note": note}  # fmt: skip
    structure = Structure(nullspace=nullspace)
    # not_converged="ignore": each row records its own outcome
    solver = KSPSolver(options, **CONVERGED | settings, structure=structure, not_converged="ignore")
    b_t = torch.from_numpy(np.asarray(b, dtype=np.float64))
    w_t = torch.from_numpy(w)
    t0 = time.perf_counter()
    try:
        th = torch.tensor(theta, dtype=torch.float64, requires_grad=True)
        sol = solve(A, b_t, solver, theta=th, return_solution=True)
        x = sol.value
        row["iterations"], row["reason"] = sol.iterations, sol.reason
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

            row["taylor_rate"], info = taylor_rate(functional, theta, grad, h)
            row["taylor_eps"] = [min(info["eps"], default=None), max(info["eps"], default=None)]
            row["taylor_noise"] = info["noise"] / max(abs(float(J.detach())), 1e-300)
        row["_x"], row["_grad"] = xn, grad
    except (SolverError, ValueError) as err:
        if isinstance(err, SolverError) and row["reason"] is None:
            row["reason"] = err.reason  # the failing solve's PETSc reason
        row["outcome"] = f"{type(err).__name__}: {getattr(err, 'reason', '') or str(err)[:60]}"
        row["message"] = str(err)
    row["seconds"] = time.perf_counter() - t0
    return row


# -- the cases -------------------------------------------------------------------------------
def case_stiff_heat(quick: bool = False) -> list[dict]:
    """Neumann heat steps ``(M + Δt K(κ)) u¹ = M u⁰`` with Δt κ / h² from 1e-2 to 1e8."""
    from skfem import Basis, ElementTriP1

    from prdp_petsc import diffusion_operator, mass_matrix

    from .problems import mean_edge_length

    mesh = _mesh("lshape", quick)
    basis = Basis(mesh, ElementTriP1())
    h, M, K = mean_edge_length(mesh), mass_matrix(basis), diffusion_operator(basis)
    x, y = mesh.p
    b = M @ np.exp(-30 * ((x - 0.25) ** 2 + (y - 0.25) ** 2))
    theta = np.ones(mesh.t.shape[1])
    return [
        evaluate("stiff heat", f"Δt κ/h² = {ratio:.0e}", (ratio * h**2) * K + M, theta, b, opts)
        for ratio in (1e-2, 1e0, 1e2, 1e4, 1e6, 1e8)
        for opts in (GAMG, ICC)
    ]


def case_contrast(quick: bool = False) -> list[dict]:
    """Dirichlet Poisson with disc inclusions or a checkerboard of contrast up to 1e8."""
    mesh = _mesh("lshape", quick)
    A, b, _ = poisson_problem(mesh)
    cx, cy = centroids(mesh)
    inside = np.zeros(cx.size, dtype=bool)
    for x0, y0 in ((0.25, 0.25), (0.25, 0.75), (0.75, 0.25)):
        inside |= (cx - x0) ** 2 + (cy - y0) ** 2 < 0.12**2
    checker = (np.floor(4 * cx) + np.floor(4 * cy)) % 2 == 0
    return [
        evaluate("contrast", f"{label} {contrast:.0e}", A, np.where(mask, contrast, 1.0), b, opts)
        for label, mask in (("inclusions", inside), ("checkerboard", checker))
        for contrast in ((1e2, 1e4, 1e8) if quick else (1e2, 1e4, 1e6, 1e8))
        for opts in (GAMG, JACOBI)
    ]


def case_anisotropy(quick: bool = False) -> list[dict]:
    """Rotated (30°) anisotropic diffusion ``−∇·(κ D ∇u) = 1``, D = R diag(1, 1/a) Rᵀ."""
    from skfem import BilinearForm

    mesh = _mesh("lshape", quick)
    c, s = np.cos(np.pi / 6), np.sin(np.pi / 6)
    R = np.array([[c, -s], [s, c]])
    rows = []
    for ratio in (1e0, 1e2, 1e4):
        D = R @ np.diag([1.0, 1.0 / ratio]) @ R.T

        @BilinearForm
        def form(u, v, w, D=D):
            du, dv = u.grad, v.grad
            return w.kappa * (du[0] * (D[0, 0] * dv[0] + D[0, 1] * dv[1])
                              + du[1] * (D[1, 0] * dv[0] + D[1, 1] * dv[1]))  # fmt: skip

        A, b, _ = poisson_problem(mesh, form=form)
        theta = np.ones(mesh.t.shape[1])
        for opts in (GAMG, ICC):
            rows.append(evaluate("anisotropy", f"ratio {ratio:.0e}, 30°", A, theta, b, opts))
    return rows


def case_neumann(quick: bool = False) -> list[dict]:
    """Pure Neumann Poisson: constant null space, compatible and incompatible rhs."""
    from skfem import LinearForm

    mesh = _mesh("lshape", quick)
    A, _, basis = poisson_problem(mesh, dirichlet=False)

    @LinearForm
    def load(v, w):  # a load with non-zero mean
        return (np.cos(np.pi * w.x[0]) * np.cos(np.pi * w.x[1]) + 0.3 * w.x[0]) * v

    b = load.assemble(basis)
    compatible = b - b.mean()
    theta = np.ones(mesh.t.shape[1])
    rows = [
        evaluate(
            "pure Neumann", "compatible rhs", A, theta, compatible, opts, nullspace="constant"
        )  # fmt: skip
        for opts in (GAMG, JACOBI, "-ksp_type gmres -pc_type ilu")
    ]
    defect = float(np.linalg.norm(b - compatible) / np.linalg.norm(b))
    row = evaluate("pure Neumann", "incompatible rhs", A, theta, b, GAMG, nullspace="constant",
                   note=f"rhs projected onto range(A) (defect {defect:.1e}); result = solve "
                   "of projected rhs")  # fmt: skip
    ref = rows[0].get("_x")
    if "_x" in row and ref is not None:
        row["projection_error"] = float(np.linalg.norm(row["_x"] - ref) / np.linalg.norm(ref))
    return [*rows, row]


def case_sliver(quick: bool = False) -> list[dict]:
    """Dirichlet Poisson on the ``sliver`` mesh (a strip of elements with angles < 5°)."""
    from prdp_petsc.fem.meshes import min_angle_degrees

    mesh = _mesh("sliver", quick, full=2)
    A, b, _ = poisson_problem(mesh)
    theta = np.ones(mesh.t.shape[1])
    angle = f"min angle {min_angle_degrees(mesh):.1f}°"
    return [evaluate("sliver mesh", angle, A, theta, b, opts) for opts in (GAMG, ICC, JACOBI)]


def case_iterations(quick: bool = False) -> list[dict]:
    """K = 1 (rtol = 0), and K far beyond convergence with rtol = atol = 0."""
    A, b, theta = _lshape_poisson(quick)
    one = (("-ksp_type cg -pc_type none", "capped implicit gradient ≠ derivative of the "
            "1-step map"), ("-ksp_type richardson -pc_type jacobi", "idem (A depends on θ: "
            "implicit ≠ unrolled even for Jacobi)"))  # fmt: skip
    rows = [evaluate("K = 1", "rtol = 0", A, theta, b, opts, max_it=1, rtol=0.0, note=note)
            for opts, note in one]  # fmt: skip
    far = 20_000  # CG needs ~1.3k (quick) or ~2.8k (full) iterations to reach rounding
    for opts in ("-ksp_type cg -pc_type none", ICC, "-ksp_type gmres -pc_type jacobi",
                 "-ksp_type bcgs -pc_type jacobi", "-ksp_type bcgs -pc_type icc"):  # fmt: skip
        setting = f"K = {far}, rtol = atol = 0"
        rows.append(evaluate("K far beyond", setting, A, theta, b, opts, max_it=far, rtol=0.0))
    return rows


def case_magnitude(quick: bool = False) -> list[dict]:
    """Right-hand sides scaled to 1e-150, 1e150 and 1e-300."""
    A, b, theta = _lshape_poisson(quick)
    return [
        evaluate("rhs magnitude", f"‖b‖ ~ {scale:.0e}", A, theta, b * scale, opts)
        for scale in (1e-150, 1e150, 1e-300)
        for opts in (JACOBI, "-ksp_type bcgs -pc_type jacobi", "-ksp_type gmres -pc_type ilu")
    ]


def case_no_transpose(quick: bool = False) -> list[dict]:
    """PCs/KSPs without a (correct) transpose, and real breakdowns: clear errors."""
    from prdp_petsc import AdjointSettings, ParametricMatrix

    from .problems import advection

    p = advection(refine=0)
    sor, ilu = "-ksp_type gmres -pc_type sor", "-ksp_type gmres -pc_type ilu"
    explicit = AdjointSettings(options={"ksp_use_explicittranspose": True})
    cgls = AdjointSettings(options={"ksp_type": "cgls", "pc_type": "none"})
    rows = [
        evaluate("no transpose", "adjoint PC sor", p.A, p.theta, p.b, sor),
        evaluate(
            "no transpose", "adjoint PC sor, explicit Aᵀ", p.A, p.theta, p.b, sor, adjoint=explicit
        ),  # fmt: skip
        evaluate("no transpose", "adjoint KSP cgls", p.A, p.theta, p.b, ilu, adjoint=cgls),
    ]
    # BiCGStab on a skew-symmetric operator: r₀ᵀ A r₀ = 0 at once
    n = 40
    skew = sp.diags([-np.ones(n - 1), np.ones(n - 1)], [-1, 1]).tocsr()
    S = ParametricMatrix(skew.indptr, skew.indices, skew.shape, skew.data.copy(),
                         sp.csr_matrix((skew.nnz, 1)))  # fmt: skip
    e1 = np.eye(n)[0]
    rows.append(evaluate("breakdown", "skew-symmetric A", S, np.ones(1), e1,
                         "-ksp_type bcgs -pc_type none", taylor=False))  # fmt: skip
    # CG on an indefinite operator (a shifted Laplacian)
    A, b, theta = _lshape_poisson(True)
    shifted = A + (-0.5 * float(A.matrix(theta).diagonal().max())) * sp.identity(A.shape[0])
    rows.append(evaluate("breakdown", "indefinite A (CG)", shifted, theta, b,
                         "-ksp_type cg -pc_type none", taylor=False))  # fmt: skip
    return rows


#: name -> case function, in table order
CASES = {
    "stiff_heat": case_stiff_heat,
    "contrast": case_contrast,
    "anisotropy": case_anisotropy,
    "neumann": case_neumann,
    "sliver": case_sliver,
    "iterations": case_iterations,
    "magnitude": case_magnitude,
    "no_transpose": case_no_transpose,
}


def run_cases(quick: bool = False, only: list[str] | None = None) -> list[dict]:
    """Run the cases (all, or those named in `only`) and return their rows."""
    rows = []
    for name, case in CASES.items():
        if not only or name in only:
            t0 = time.perf_counter()
            rows.extend(case(quick))
            logger.info("case %s: %.1f s", name, time.perf_counter() - t0)
    return rows


# -- the table -------------------------------------------------------------------------------
def _fmt(value, spec: str) -> str:
    if value is None or (isinstance(value, float) and np.isnan(value)):
        return "—"
    return format(value, spec)


def _row_cells(r: dict) -> tuple:
    its = "—"
    if r["iterations"] is not None:
        its = f"{r['iterations']}/{_fmt(r['adjoint_iterations'], 'd')}"
    outcome = r["outcome"] + (f"; {r['note']}" if r.get("note") else "")
    lo, hi = r.get("taylor_eps") or (None, None)
    if lo is not None and lo > 2e-3:  # the smallest ε were below J's rounding noise
        outcome += f"; J rounding noise {r['taylor_noise']:.0e} (relative): ε ≥ {lo:.0e}"
    if "projection_error" in r:
        outcome += f" (vs compatible: {r['projection_error']:.1e})"
    return (r["case"], r["setting"], r["solver"], r["n"], its, r["reason"] or "—",
            _fmt(r["residual"], ".1e"), _fmt(r["taylor_rate"], ".2f"),
            "—" if lo is None else f"{lo:.0e}–{hi:.0e}", "yes" if r["nan_or_inf"] else "no",
            outcome)  # fmt: skip


def to_markdown(rows: list[dict]) -> str:
    """The rows as a markdown table."""
    header = ["case", "setting", "KSP/PC", "n", "its fwd/adj", "reason", "‖b−Ax‖/‖b‖",
              "Taylor rate", "Taylor ε", "NaN/Inf", "outcome"]  # fmt: skip
    return markdown_table(header, map(_row_cells, rows), "lllrrlrrlll") + "\n"


def summary_counts(rows: list[dict]) -> dict:
    """What the suite's rows say: how many solved, with a right gradient, raised, NaN."""
    ok = [r for r in rows if r["outcome"] == "ok"]
    rates = [r.get("taylor_rate") for r in ok]
    return {
        "rows": len(rows),
        "ok": len(ok),
        "right": sum(x is not None and x >= TAYLOR_RIGHT for x in rates),  # NaN: False
        "errors": sorted({r["outcome"] for r in rows if r["outcome"] != "ok"}),
        "nan_or_inf": sum(bool(r["nan_or_inf"]) for r in rows),
        "cases": len(dict.fromkeys(r["case"] for r in rows)),
    }


def summary_line(c: dict) -> str:
    """`summary_counts` as one sentence (results pages, headline table)."""
    return (
        f"{c['ok']} solved, {c['right']} of them with a Taylor rate ≥ {TAYLOR_RIGHT} "
        f"(2: the gradient is right); {c['rows'] - c['ok']} raised the error they must "
        f"({', '.join(c['errors'])}); NaN or Inf in {c['nan_or_inf']}"
    )


def main(argv: list[str] | None = None) -> int:
    """``prdp-petsc stability --out DIR [--preset quick] [--cases NAME ...]``."""
    from ..cli.arguments import add_debug, add_out, add_size_preset

    parser = argparse.ArgumentParser(
        prog="prdp-petsc stability",
        description="Stability suite of capped PETSc solves and their gradients; writes "
        "DIR/stability.json and DIR/stability.md.",
    )
    add_out(parser)
    add_size_preset(parser, "small meshes (seconds)")
    parser.add_argument("--cases", nargs="*", choices=sorted(CASES), help="run only these")
    add_debug(parser)
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    quick = args.preset == "quick"
    rows = run_cases(quick, args.cases)
    public = [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows]
    meta = {"quick": quick, "seconds": time.perf_counter() - t0}
    write_result(args.out, "stability.json", {"meta": meta, "rows": public})
    (args.out / "stability.md").write_text(to_markdown(rows))
    print(f"stability: {len(rows)} rows in {meta['seconds']:.0f} s -> {args.out}/stability.md")
    return 1 if any(r["nan_or_inf"] for r in rows) else 0


# -- the page of a recorded ``stability`` run ----------------------------------------------------
def _summary(ds: DataSet) -> str:
    c = summary_counts(ds.main["rows"])
    return f"{c['rows']} rows in {c['cases']} cases: {summary_line(c)}."


def _headline(ds: DataSet) -> list[tuple[str, str]]:
    c = summary_counts(ds.main["rows"])
    return [(f"stability suite: {c['rows']} stiff and extreme solves", summary_line(c))]


KIND = ReportKind(
    name="stability",
    reads="stability.json",
    title=lambda ds: "Stability on stiff and extreme cases",
    headline=_headline,
    intro="Each row solves `A(θ) x = b` through the torch bridge and reports the forward "
    "residual, the iterations (forward/adjoint), the Taylor rate of the gradient of "
    "`J(θ) = ⟨w, x(θ)⟩` (2 when the gradient is right) with the ε range of the fit, "
    "whether anything became NaN/Inf, and the outcome; a case that must fail reports "
    "the error and the PETSc reason. The cases are described in the docstring of "
    "`prdp_petsc.lab.reports.stability`; `tests/lab/test_stability.py` runs them at "
    "small sizes.",
    output=_summary,
    printed=False,
    after=lambda ds: [to_markdown(ds.main["rows"]).rstrip("\n")],
)
