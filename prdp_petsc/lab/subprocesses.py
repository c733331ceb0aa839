"""The environment of a child process the lab starts (a recorded command, an MPI job)."""

from __future__ import annotations

import os

__all__ = ["child_env"]

# what Open MPI's runtime puts into the environment of a process that initialised MPI
# alone (a singleton): a child started with it takes itself for a rank of that job
_RUNTIME_PREFIXES = ("PMIX_", "ORTE_", "OMPI_MCA_orte_", "OMPI_APP_CTX_")
_RUNTIME_NAMES = {"OMPI_MCA_ess", "OMPI_MCA_pmix", "IPATH_NO_BACKTRACE", "HFI_NO_BACKTRACE"}


def child_env(extra: dict | None = None) -> dict:
    """This process's environment without the MPI runtime's variables, plus `extra`: a
    child that starts its own MPI job fails with the variables Open MPI put into
    ``os.environ`` after ``MPI_Init`` here (the user's own ``OMPI_*`` settings stay)."""
    env = {
        key: value
        for key, value in os.environ.items()
        if not key.startswith(_RUNTIME_PREFIXES) and key not in _RUNTIME_NAMES
    }
    return {**env, **(extra or {})}
