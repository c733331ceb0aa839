"""torch layer: differentiable capped solves (implicit, unrolled), Dirichlet, Newton/Picard."""
