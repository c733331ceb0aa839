"""Heat 2D emulator on an unstructured mesh, trained through a capped PETSc solve.

PDE: u_t = ∇·(κ∇u) on the L-shaped domain (the shipped gmsh mesh ``lshape``),
u = 0 on the boundary, κ = 1.  Discretisation: P1 finite elements (scikit-fem),
implicit Euler, one step ``(M + Δt K) uⁿ⁺¹ = M uⁿ`` on the interior nodes
(Dirichlet nodes eliminated).  Initial conditions: sums of random Gaussian bumps
times the bubble (−Δd = 1), so they vanish smoothly on the boundary.

Solver in the loop: damped Jacobi (``richardson`` + ``jacobi``, scale 0.8, the
paper's solver) in fixed mode, K = ``max_it`` iterations; implicit (adjoint)
gradients.  The solve starts from its input ûⁿ⁺¹ (``solve(..., x0=)``, PETSc's
nonzero initial guess), as a time stepper would: the step changes smooth fields
little, so the slow, smooth Jacobi modes start almost converged (``warm_start:
False`` starts from zero; the scenes guide says what that costs).  K_full counts the
iterations from the guess to PETSc's default test ``‖r‖ ≤ 10⁻⁶ ‖b‖``, so the
full-fidelity baseline gains from the guess too.  Any PETSc solver is one option
away (``-heat2d_ksp_type cg -heat2d_pc_type icc``); ``compare --routes cg/icc`` runs
PRDP and full fidelity with it as well and says which route is fastest.

Learning problem (the paper's mixed chain): a network N maps uⁿ to ûⁿ⁺¹, the
loss compares the *capped* solver step P_K(ûⁿ⁺¹) with the exact uⁿ⁺², so a
small K biases what N learns.  Training pairs (uₜ, uₜ₊₂) start at t = 0, …,
``spans`` − 1 of each training trajectory, so N sees the smoother states a rollout
meets, not only initial conditions.  N is a `prdp_petsc.lab.components.modal.ModalNet`:
one learned weight per eigenmode of ``K φ = λ M φ`` (the mesh's Fourier basis;
the spectral layer of a Fourier neural operator), ``modes`` of them (why not a
message-passing `~prdp_petsc.lab.components.networks.MeshNet`: the known limitations).
Modal coefficients are M-orthonormal, each weight is fitted by its own mode, and the
modes N drops are those the step damps most.  Validation metric: the mean
normalised error of a 10-step autoregressive rollout of N on held-out initial
conditions; the harness also records a 30-step rollout curve.

Multi-step training (``unroll`` = m, 1 in every preset): the chain s ← P_K(B N(s))
runs m times from each training state uₜ, and the loss sums the misfits of its
states against the exact uₜ₊₂, …, uₜ₊₂ₘ (`heat_emulator_scene`); m = 1 is the
one-step chain above.

Presets: ``quick`` (tests), ``paper`` (5 457 unknowns, Δt κ/h² ≈ 1.2) and
``stiff`` (Δt κ/h² ≈ 6e3, where damped Jacobi is slow and the PC choice decides).
``paper_mlp`` is ``paper`` with the reference's emulator class instead of ModalNet
(``net: "mlp"``: a `~prdp_petsc.lab.components.networks.ResidualMLP` over the nodal
values) and 64 training trajectories.  ``routes`` names the KSP/PC pairs ``compare``
also runs: the step matrix M + Δt K is SPD, so CG with ICC or GAMG.  The scene is
`prdp_petsc.lab.components.emulators.heat_emulator_build`, shared with heat3d; this
file holds its presets and its options prefix ``heat2d_``.

Run ``python demos/heat2d.py compare --preset paper --routes cg/icc --out results/heat2d``.
"""

from __future__ import annotations

from prdp_petsc import lab
from prdp_petsc.lab.components.emulators import heat_emulator_build

PRESETS = {
    "quick": {
        "mesh": "lshape",
        "refine": 0,
        "dt": 1e-3,
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
        "k_init": 4,
        "k_step": 4,
        "routes": "cg/icc",
    },
    "paper": {
        "mesh": "lshape",
        "refine": 1,
        "dt": 2e-4,
        "net": "modal",
        "modes": 128,
        "width": 128,
        "depth": 2,
        "warm_start": True,
        "spans": 6,
        "n_train": 32,
        "n_val": 8,
        "val_steps": 10,
        "rollout_steps": 30,
        "unroll": 1,
        "epochs": 20,
        "batch": 16,
        "lr": 2e-2,
        "gamma": 0.9,
        "k_init": 10,
        "k_step": 20,
        "routes": "cg/icc,cg/gamg",
    },
    "stiff": {
        "mesh": "lshape",
        "refine": 1,
        "dt": 1.0,
        "net": "modal",
        "modes": 64,
        "width": 128,
        "depth": 2,
        "warm_start": True,
        "spans": 4,
        "n_train": 16,
        "n_val": 8,
        "val_steps": 10,
        "rollout_steps": 20,
        "unroll": 1,
        "epochs": 10,
        "batch": 16,
        "lr": 2e-2,
        "gamma": 0.9,
        "k_init": 50,
        "k_step": 50,
        "routes": "cg/icc,cg/gamg",
    },
}

# the reference's emulator class: a residual MLP over the nodal values
_MLP = {"net": "mlp", "lr": 1e-3, "gamma": 0.95, "k_init": 4, "k_step": 4}
PRESETS["paper_mlp"] = {**PRESETS["paper"], **_MLP, "n_train": 64}


def build(config: dict, seed: int) -> lab.Scene:
    return heat_emulator_build(config, seed, prefix="heat2d_")


if __name__ == "__main__":
    from prdp_petsc.lab.cli import scene_main

    raise SystemExit(scene_main(__file__))
