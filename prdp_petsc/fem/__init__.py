"""Assembly layer: parametric sparse operators from scikit-fem forms, finite differences, meshes.

Nothing here imports PETSc or torch: operators are scipy CSR matrices (or
`ParametricMatrix` with values ``a0 + G θ``) that the core layer turns into Mats.
"""
