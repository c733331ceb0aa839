"""torch layer: differentiable capped solves (implicit, unrolled), Dirichlet, Newton/Picard.

`WarmStarts` (`prdp_petsc.autograd.warm_starts`) keeps each training sample's last
solution as its next initial guess (``solve(..., x0=starts.guess(idx))``).
"""

from .warm_starts import WarmStarts

__all__ = ["WarmStarts"]
