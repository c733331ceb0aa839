"""Physics and networks the shipped scenes (demos/) and the lab's reports share.

`mac` (the staggered incompressible Navier-Stokes grid of ns2d and its tests),
`emulators` (random smooth fields, torch sparse matrices) and `networks` (an MLP).
"""
