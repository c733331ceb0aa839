"""Physics and networks used only by the shipped scenes (demos/), not by the library.

`mac` (the staggered incompressible Navier-Stokes grid of ns2d), `nonlinear_heat`
(the κ(u) heat step of heat_nonlinear), `emulators` (the learned-emulator scene
builder of heat2d/heat3d), `modal` and `networks` (the scenes' network classes).
"""
