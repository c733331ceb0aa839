"""Assembly layer: scikit-fem operators (parametric, nonlinear heat), finite differences, meshes.

Nothing here imports PETSc or torch: operators are scipy CSR matrices (or
`ParametricMatrix` with values ``a0 + G θ``) that the core layer turns into Mats.
"""
