"""Stability suite: hard linear problems through capped PETSc solves and their gradients.

Each case solves ``A(θ) x = b`` through the torch bridge (`prdp_petsc.solve`) and
reports the forward residual ``‖b − A x‖/‖b‖``, the forward and adjoint iteration
counts, the Taylor rate of the gradient of ``J(θ) = ⟨w, x(θ)⟩`` (2 when the
gradient is right, 1 when it is inconsistent) and whether anything became NaN/Inf;
a case that must fail reports the error type and PETSc reason.  Cases:

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
import json
import logging
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from .kinds import DataSet, ReportKind
from .stability_rows import centroids, evaluate, poisson_problem, taylor_rate, to_markdown

__all__ = [
    "CASES",
    "KIND",
    "TAYLOR_RIGHT",
    "main",
    "run_cases",
    "summary_counts",
    "summary_line",
    "taylor_rate",
    "to_markdown",
]

logger = logging.getLogger(__name__)


GAMG = "-ksp_type cg -pc_type gamg"


def case_stiff_heat(quick: bool = False) -> list[dict]:
    """Neumann heat steps ``(M + Δt K(κ)) u¹ = M u⁰`` with Δt κ / h² from 1e-2 to 1e8."""
    from skfem import Basis, ElementTriP1

    from prdp_petsc import diffusion_operator, load_mesh, mass_matrix

    from .problems import mean_edge_length

    mesh = load_mesh("lshape", 0 if quick else 1)
    basis = Basis(mesh, ElementTriP1())
    h = mean_edge_length(mesh)
    M = mass_matrix(basis)
    K = diffusion_operator(basis)
    x, y = mesh.p
    b = M @ np.exp(-30 * ((x - 0.25) ** 2 + (y - 0.25) ** 2))
    theta = np.ones(mesh.t.shape[1])
    rows = []
    for ratio in (1e-2, 1e0, 1e2, 1e4, 1e6, 1e8):
        A = (ratio * h**2) * K + M
        for options in (GAMG, "-ksp_type cg -pc_type icc"):
            rows.append(evaluate("stiff heat", f"Δt κ/h² = {ratio:.0e}", A, theta, b, options))
    return rows


def case_contrast(quick: bool = False) -> list[dict]:
    """Dirichlet Poisson with disc inclusions or a checkerboard of contrast up to 1e8."""
    from prdp_petsc import load_mesh

    mesh = load_mesh("lshape", 0 if quick else 1)
    A, b, _ = poisson_problem(mesh)
    cx, cy = centroids(mesh)
    discs = ((0.25, 0.25), (0.25, 0.75), (0.75, 0.25))
    inside = np.zeros(cx.size, dtype=bool)
    for x0, y0 in discs:
        inside |= (cx - x0) ** 2 + (cy - y0) ** 2 < 0.12**2
    checker = (np.floor(4 * cx) + np.floor(4 * cy)) % 2 == 0
    rows = []
    for label, mask in (("inclusions", inside), ("checkerboard", checker)):
        for contrast in (1e2, 1e4, 1e8) if quick else (1e2, 1e4, 1e6, 1e8):
            theta = np.where(mask, contrast, 1.0)
            for options in (GAMG, "-ksp_type cg -pc_type jacobi"):
                rows.append(evaluate("contrast", f"{label} {contrast:.0e}", A, theta, b, options))
    return rows


def case_anisotropy(quick: bool = False) -> list[dict]:
    """Rotated (30°) anisotropic diffusion ``−∇·(κ D ∇u) = 1``, D = R diag(1, 1/a) Rᵀ."""
    from skfem import BilinearForm

    from prdp_petsc import load_mesh

    mesh = load_mesh("lshape", 0 if quick else 1)
    rows = []
    c, s = np.cos(np.pi / 6), np.sin(np.pi / 6)
    for ratio in (1e0, 1e2, 1e4):
        R = np.array([[c, -s], [s, c]])
        D = R @ np.diag([1.0, 1.0 / ratio]) @ R.T

        @BilinearForm
        def form(u, v, w, D=D):
            du, dv = u.grad, v.grad
            return w.kappa * (
                du[0] * (D[0, 0] * dv[0] + D[0, 1] * dv[1])
                + du[1] * (D[1, 0] * dv[0] + D[1, 1] * dv[1])
            )

        A, b, _ = poisson_problem(mesh, form=form)
        theta = np.ones(mesh.t.shape[1])
        for options in (GAMG, "-ksp_type cg -pc_type icc"):
            rows.append(evaluate("anisotropy", f"ratio {ratio:.0e}, 30°", A, theta, b, options))
    return rows


def case_neumann(quick: bool = False) -> list[dict]:
    """Pure Neumann Poisson: constant null space, compatible and incompatible rhs."""
    from prdp_petsc import load_mesh

    mesh = load_mesh("lshape", 0 if quick else 1)
    A, _, basis = poisson_problem(mesh, dirichlet=False)
    x, y = mesh.p
    f = np.cos(np.pi * x) * np.cos(np.pi * y) + 0.3 * x  # a load with non-zero mean
    from skfem import LinearForm

    @LinearForm
    def load(v, w):
        return (np.cos(np.pi * w.x[0]) * np.cos(np.pi * w.x[1]) + 0.3 * w.x[0]) * v

    b = load.assemble(basis)
    compatible = b - b.mean()
    theta = np.ones(mesh.t.shape[1])
    del f
    rows = []
    for options in (GAMG, "-ksp_type cg -pc_type jacobi", "-ksp_type gmres -pc_type ilu"):
        rows.append(
            evaluate(
                "pure Neumann",
                "compatible rhs",
                A,
                theta,
                compatible,
                options,
                nullspace="constant",
            )
        )
    defect = float(np.linalg.norm(b - compatible) / np.linalg.norm(b))
    row = evaluate(
        "pure Neumann",
        "incompatible rhs",
        A,
        theta,
        b,
        GAMG,
        nullspace="constant",
        note=f"rhs projected onto range(A) (defect {defect:.1e}); result = solve of projected rhs",
    )
    ref = rows[0].get("_x")
    if "_x" in row and ref is not None:
        row["projection_error"] = float(np.linalg.norm(row["_x"] - ref) / np.linalg.norm(ref))
    rows.append(row)
    return rows


def case_sliver(quick: bool = False) -> list[dict]:
    """Dirichlet Poisson on the ``sliver`` mesh (a strip of elements with angles < 5°)."""
    from prdp_petsc import load_mesh
    from prdp_petsc.fem.meshes import min_angle_degrees

    mesh = load_mesh("sliver", 0 if quick else 2)
    A, b, _ = poisson_problem(mesh)
    theta = np.ones(mesh.t.shape[1])
    angle = f"min angle {min_angle_degrees(mesh):.1f}°"
    return [
        evaluate("sliver mesh", angle, A, theta, b, options)
        for options in (GAMG, "-ksp_type cg -pc_type icc", "-ksp_type cg -pc_type jacobi")
    ]


def _lshape_poisson(quick: bool):
    from prdp_petsc import load_mesh

    mesh = load_mesh("lshape", 0 if quick else 1)
    A, b, _ = poisson_problem(mesh)
    return A, b, np.ones(mesh.t.shape[1])


def case_iterations(quick: bool = False) -> list[dict]:
    """K = 1 (rtol = 0), and K far beyond convergence with rtol = atol = 0."""
    A, b, theta = _lshape_poisson(quick)
    rows = [
        evaluate(
            "K = 1",
            "rtol = 0",
            A,
            theta,
            b,
            "-ksp_type cg -pc_type none",
            max_it=1,
            rtol=0.0,
            note="capped implicit gradient ≠ derivative of the 1-step map",
        ),
        evaluate(
            "K = 1",
            "rtol = 0",
            A,
            theta,
            b,
            "-ksp_type richardson -pc_type jacobi",
            max_it=1,
            rtol=0.0,
            note="idem (A depends on θ: implicit ≠ unrolled even for Jacobi)",
        ),
    ]
    far = 20_000  # CG needs ~1.3k (quick) or ~2.8k (full) iterations to reach rounding
    for options in (
        "-ksp_type cg -pc_type none",
        "-ksp_type cg -pc_type icc",
        "-ksp_type gmres -pc_type jacobi",
        "-ksp_type bcgs -pc_type jacobi",
        "-ksp_type bcgs -pc_type icc",
    ):
        rows.append(
            evaluate(
                "K far beyond",
                f"K = {far}, rtol = atol = 0",
                A,
                theta,
                b,
                options,
                max_it=far,
                rtol=0.0,
            )
        )
    return rows


def case_magnitude(quick: bool = False) -> list[dict]:
    """Right-hand sides scaled to 1e-150, 1e150 and 1e-300."""
    A, b, theta = _lshape_poisson(quick)
    rows = []
    for scale in (1e-150, 1e150, 1e-300):
        for options in (
            "-ksp_type cg -pc_type jacobi",
            "-ksp_type bcgs -pc_type jacobi",
            "-ksp_type gmres -pc_type ilu",
        ):
            rows.append(
                evaluate("rhs magnitude", f"‖b‖ ~ {scale:.0e}", A, theta, b * scale, options)
            )
    return rows


def case_no_transpose(quick: bool = False) -> list[dict]:
    """PCs/KSPs without a (correct) transpose, and real breakdowns: clear errors."""
    from prdp_petsc import AdjointSettings

    from .problems import advection

    p = advection(refine=0)
    rows = [
        evaluate(
            "no transpose", "adjoint PC sor", p.A, p.theta, p.b, "-ksp_type gmres -pc_type sor"
        ),
        evaluate(
            "no transpose",
            "adjoint PC sor, explicit Aᵀ",
            p.A,
            p.theta,
            p.b,
            "-ksp_type gmres -pc_type sor",
            adjoint=AdjointSettings(options={"ksp_use_explicittranspose": True}),
        ),
        evaluate(
            "no transpose",
            "adjoint KSP cgls",
            p.A,
            p.theta,
            p.b,
            "-ksp_type gmres -pc_type ilu",
            adjoint=AdjointSettings(options={"ksp_type": "cgls", "pc_type": "none"}),
        ),
    ]
    # BiCGStab on a skew-symmetric operator: r₀ᵀ A r₀ = 0 at once
    from prdp_petsc import ParametricMatrix

    n = 40
    skew = sp.diags([-np.ones(n - 1), np.ones(n - 1)], [-1, 1]).tocsr()
    S = ParametricMatrix(
        skew.indptr, skew.indices, skew.shape, skew.data.copy(), sp.csr_matrix((skew.nnz, 1))
    )
    e1 = np.zeros(n)
    e1[0] = 1.0
    rows.append(
        evaluate(
            "breakdown",
            "skew-symmetric A",
            S,
            np.ones(1),
            e1,
            "-ksp_type bcgs -pc_type none",
            taylor=False,
        )
    )
    # CG on an indefinite operator (a shifted Laplacian)
    A, b, theta = _lshape_poisson(True)
    shift = 0.5 * float(A.matrix(theta).diagonal().max())
    rows.append(
        evaluate(
            "breakdown",
            "indefinite A (CG)",
            A + (-shift) * sp.identity(A.shape[0]),
            theta,
            b,
            "-ksp_type cg -pc_type none",
            taylor=False,
        )
    )
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
        if only and name not in only:
            continue
        t0 = time.perf_counter()
        rows.extend(case(quick))
        logger.info("case %s: %.1f s", name, time.perf_counter() - t0)
    return rows


#: a Taylor rate at or above this says the gradient is right (2 in exact arithmetic)
TAYLOR_RIGHT = 1.85


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
    from ..cli.arguments import add_debug, add_size_preset

    parser = argparse.ArgumentParser(
        prog="prdp-petsc stability",
        description="Stability suite of capped PETSc solves and their gradients; writes "
        "DIR/stability.json and DIR/stability.md.",
    )
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    add_size_preset(parser, "small meshes (seconds)")
    parser.add_argument("--cases", nargs="*", choices=sorted(CASES), help="run only these")
    add_debug(parser)
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    quick = args.preset == "quick"
    rows = run_cases(quick, args.cases)
    args.out.mkdir(parents=True, exist_ok=True)
    public = [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows]
    meta = {"quick": quick, "seconds": time.perf_counter() - t0}
    (args.out / "stability.json").write_text(json.dumps({"meta": meta, "rows": public}, indent=1))
    (args.out / "stability.md").write_text(to_markdown(rows))
    failed = [r for r in rows if r["nan_or_inf"]]
    print(f"stability: {len(rows)} rows in {meta['seconds']:.0f} s -> {args.out}/stability.md")
    return 1 if failed else 0


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


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
