"""Physics and networks the shipped scenes (demos/) and the lab's reports share.

`mac` (the staggered incompressible Navier-Stokes grid of ns2d), `nonlinear_heat`
(the κ(u) heat step of heat_nonlinear), `emulators` (random smooth fields, torch
sparse matrices) and `networks` (the scenes' network classes).
"""
