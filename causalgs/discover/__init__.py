"""`causalgs discover`: where simulation and measurement disagree, which physical effect is missing, and the fix.

The workflow (``../shared/DISCOVERY.md`` has the candidate catalogue and why each step is there):
:mod:`observation` (the measured trajectories), :mod:`model` (the particles, per-body parameters and effects that
are calibrated), :mod:`calibrate` (least squares through the differentiable MPM, from several stiffnesses).
"""
