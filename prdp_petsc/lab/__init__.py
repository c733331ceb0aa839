"""The lab: the experiment machinery around the prdp_petsc library.

Installed with the ``lab`` extra (``pip install "prdp-petsc[lab]"``: matplotlib and
tqdm).  It holds the scene protocol (`prdp_petsc.lab.training.scene.Scene`), the
training harness, PRDP-against-full comparisons over seeds and routes, the reports
and benchmarks, the generated results pages and the ``prdp-petsc`` command
(`prdp_petsc.lab.cli`).  `prdp_petsc.lab.components` holds the physics and networks
that only the shipped scenes use.

The lab uses only the library's public names (``import prdp_petsc as pp``); the
library imports nothing from here.
"""

from importlib import import_module

# public name -> module that defines it (imported on first use, as in prdp_petsc)
_EXPORTS = {
    "Scene": ".training.scene",
    "NonlinearHeat": ".components.nonlinear_heat",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(import_module(_EXPORTS[name], __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
