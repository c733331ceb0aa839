"""Heat 3D emulator on a tetrahedral mesh, trained through a capped PETSc solve.

PDE: u_t = ∇·(κ∇u) in the unit cube (the shipped gmsh mesh ``box3d``, refined
once in the ``paper`` preset: 5 146 unknowns, 39 544 tetrahedra), u = 0 on the
boundary, κ = 1.  Discretisation: P1 finite elements (scikit-fem), implicit Euler,
one step ``(M + Δt K) uⁿ⁺¹ = M uⁿ`` on the interior nodes (Dirichlet nodes
eliminated), Δt κ/h² ≈ 0.7 with the mean edge h.  Initial conditions: sums of
random Gaussian bumps times the bubble (−Δd = 1), so they vanish smoothly on the
boundary.

Solver in the loop: damped Jacobi (``richardson`` + ``jacobi``, scale 0.8) in fixed
mode, K = ``max_it`` iterations from the input ûⁿ⁺¹ as initial guess (see heat2d),
implicit (adjoint) gradients; the same scene as ``heat2d`` (both built by
`prdp_petsc.lab.components.emulators.heat_emulator_build`), so ``-heat3d_ksp_type cg
-heat3d_pc_type icc`` and ``compare --routes cg/icc`` work the same way.  The mesh is
sized so that the solve dominates training (``compare`` reports the solver's share of
the wall time), so PRDP's savings in iterations show in wall time.

Learning problem (the paper's mixed chain): a network N maps uⁿ to ûⁿ⁺¹ and the loss
compares the capped solver step P_K(ûⁿ⁺¹) with the exact uⁿ⁺².  Training pairs
(uₜ, uₜ₊₂) start at t = 0, …, ``spans`` − 1 of each training trajectory, so N sees
the states a rollout meets.  N is a `prdp_petsc.lab.components.modal.ModalNet`, as in
heat2d: one learned weight per eigenmode of ``K φ = λ M φ`` (the mesh's Fourier
basis), the ``modes`` lowest.  Modal weights are fitted each by its own mode, and the
modes N drops are those the step damps most and cannot be amplified; a kept mode's
weight above 1 still grows in a rollout.  Validation metric: the mean normalised error of
a 10-step autoregressive rollout on held-out initial conditions; the harness also
records a 20-step curve.
``unroll`` = m > 1 trains on m chained steps instead of one, as in heat2d.

Presets: ``quick`` (tests; 465 unknowns) and ``paper``, heat2d's settings on the cube
(another mesh and time step); ``routes`` as in heat2d (the step matrix is SPD).

Run ``python demos/heat3d.py compare --preset paper --routes cg/icc --out results/heat3d``.
"""

from __future__ import annotations

from prdp_petsc import lab
from prdp_petsc.lab.components.emulators import heat_emulator_build

PRESETS = {
    "quick": {
        "mesh": "box3d",
        "refine": 0,
        "dt": 1e-2,
        "net": "modal",
        "modes": 16,
        "width": 128,
        "depth": 2,
        "warm_start": True,
        "spans": 4,
        "n_train": 8,
        "n_val": 4,
        "val_steps": 10,
        "rollout_steps": 20,
        "unroll": 1,
        "epochs": 8,
        "batch": 8,
        "lr": 3e-2,
        "gamma": 0.9,
        "k_init": 16,
        "k_step": 16,
        "routes": "cg/icc",
    },
    "paper": {
        "mesh": "box3d",
        "refine": 1,
        "dt": 3e-3,
        "net": "modal",
        "modes": 128,
        "width": 128,
        "depth": 2,
        "warm_start": True,
        "spans": 6,
        "n_train": 32,
        "n_val": 8,
        "val_steps": 10,
        "rollout_steps": 20,
        "unroll": 1,
        "epochs": 20,
        "batch": 16,
        "lr": 2e-2,
        "gamma": 0.9,
        "k_init": 10,
        "k_step": 20,
        "routes": "cg/icc,cg/gamg",
    },
}


def build(config: dict, seed: int) -> lab.Scene:
    return heat_emulator_build(config, seed, prefix="heat3d_")


if __name__ == "__main__":
    from prdp_petsc.lab.cli import scene_main

    raise SystemExit(scene_main(__file__))
