"""PETSc layer: capped KSP solves, options, operators as Mats, safeguards, null spaces.

Nothing here imports torch; `prdp_petsc.autograd` connects these solvers to
autograd.  The package imports nothing eagerly: the command line initialises
PETSc with its options before the first PETSc import.
"""
