"""Physics and networks the shipped scenes (demos/) and the lab's reports share.

`mac` (the staggered Navier-Stokes grid of ns2d, a module of its own because ns2d's
reference data on disk are keyed on its source), `emulators` (random smooth fields,
torch sparse matrices) and `networks` (an MLP).
"""
