"""PETSc layer: capped KSP solves, options, operators as Mats, safeguards, null spaces.

Nothing here imports torch; `prdp_petsc.autograd` connects these solvers to autograd.
"""
