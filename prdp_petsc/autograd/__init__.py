"""torch layer: differentiable capped solves (implicit and unrolled) and Dirichlet lifting."""
