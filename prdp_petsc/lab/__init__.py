"""The lab: the experiment machinery around the prdp_petsc library (the ``lab`` extra).

The scene protocol (`prdp_petsc.lab.training.scene.Scene`), the training harness,
comparisons over seeds and routes, reports, benchmarks, the generated results pages
and the ``prdp-petsc`` command (`prdp_petsc.lab.cli`); `prdp_petsc.lab.components`
holds what only the shipped scenes use.  It uses only the library's public names.
"""

from importlib import import_module

# public name -> module that defines it (imported on first use, as in prdp_petsc)
_EXPORTS = {"Scene": ".training.scene"}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(import_module(_EXPORTS[name], __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
