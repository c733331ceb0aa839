"""The ``prdp-petsc`` command line.

Sub-commands::

    prdp-petsc run SCENE_FILE [--schedule prdp|auto|rtol|fixed:K] [--preset quick|paper]
                   [--set KEY=VALUE ...] [--k-max full|none|K] [--epochs N] [--seed S]
                   [--threads T] [--parallel domain|batch] [--checkpoint-every N]
                   --out DIR [PETSc options]
    prdp-petsc run --resume DIR [--epochs N] [--threads T] [PETSc options]
    prdp-petsc compare SCENE_FILE [--preset ...] [--set KEY=VALUE ...] [--epochs N]
                   [--seed S | --seeds 0-3] [--threads T] [--routes cg/icc,cg/gamg]
                   [--schedules prdp,rtol] [--parallel domain|batch]
                   [--checkpoint-every N] [--resume]
                   --out DIR [PETSc options]
    prdp-petsc scene SCENE_FILE [NAME [ARGS ...]] [--debug] [PETSc options]
    prdp-petsc COMMAND -h   (the report tools listed below: bench, work-precision, ...)
    prdp-petsc --version

Every sub-command follows the same conventions: PETSc options (single dash, such as
``-heat_ksp_type cg -log_view``) start PETSc, ``--debug`` shows the traceback of an
error (otherwise one line, exit status 1), a usage error exits 2, Ctrl-C exits 130
(the results written so far stay), and a concept has one spelling
(`prdp_petsc.lab.cli.arguments`).  Warning filters that name a category of this
package (``-W error::prdp_petsc.errors.UnusedOptionWarning``) apply from the start
(`apply_warning_options`).
"""

from .dispatch import main, scene_main
from .petsc import apply_warning_options, init_petsc, split_petsc_options

__all__ = ["apply_warning_options", "init_petsc", "main", "scene_main", "split_petsc_options"]
