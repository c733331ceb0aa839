"""Reports: bridge benchmark, work-precision and stability suites (and their test problems).

matplotlib is imported only here and in `prdp_petsc.lab.training.plots`.
"""
