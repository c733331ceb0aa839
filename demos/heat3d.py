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
implicit (adjoint) gradients; the same
scene as ``heat2d`` (built by its `build_emulator`), so
``-heat3d_ksp_type cg -heat3d_pc_type icc`` and ``compare --routes cg/icc`` work
the same way.  The mesh is sized so that the solve dominates training: at K_full
the solver takes most of each epoch's wall time (`solver %` in compare's table), so
PRDP's savings in iterations show in wall time.

Learning problem (the paper's mixed chain): a network N maps uⁿ to ûⁿ⁺¹ and the loss
compares the capped solver step P_K(ûⁿ⁺¹) with the exact uⁿ⁺².  Training pairs
(uₜ, uₜ₊₂) start at t = 0, …, ``spans`` − 1 of each training trajectory, so N sees
the states a rollout meets.  N is a `prdp_petsc.training.modal.ModalNet`, as in
heat2d: one learned weight per eigenmode of ``K φ = λ M φ`` (the mesh's Fourier
basis), the ``modes`` lowest.  The message-passing `MeshNet` that heat2d used
before does not emulate this step: trained through the solve, its rollouts
drifted or diverged (the solve damps the high-frequency part of N's error, so the
loss barely constrains a local network there).  Modal weights are fitted each by
its own mode, and the modes N drops are those the step damps most and cannot be
amplified; a kept mode's weight above 1 still grows in a rollout (as at K = 1).
Validation metric: the mean normalised error of
a 10-step autoregressive rollout on held-out initial conditions; the harness also
records a 20-step curve.

Presets: ``quick`` (tests; 465 unknowns, seconds) and ``paper``.

Run ``python demos/heat3d.py compare --preset paper --routes cg/icc --out results/heat3d``.
"""

from __future__ import annotations

from pathlib import Path

import prdp_petsc as pp
from prdp_petsc.training.scene import load_scene

_HEAT2D = load_scene(Path(__file__).with_name("heat2d.py"))

# heat2d's presets on the cube: another mesh and time step (Δt κ/h² ≈ 0.7 on `paper`)
PRESETS = {
    "quick": {**_HEAT2D.PRESETS["quick"], "mesh": "box3d", "dt": 1e-2, "k_init": 16, "k_step": 16},
    "paper": {**_HEAT2D.PRESETS["paper"], "mesh": "box3d", "dt": 3e-3, "rollout_steps": 20},
}


def build(config: dict, seed: int) -> pp.Scene:
    return _HEAT2D.build_emulator(config, seed, prefix="heat3d_")


if __name__ == "__main__":
    from prdp_petsc.cli import scene_main

    raise SystemExit(scene_main(__file__))
