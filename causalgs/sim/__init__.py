"""Differentiable MLS-MPM: kernels, constitutive models, external effects and the simulator loop.

- :class:`Simulator`, :class:`SimConfig` (:mod:`causalgs.sim.mpm`): time stepping over a ParticleStore.
- :mod:`causalgs.sim.materials`: ``MODELS`` (neo_hookean, stvk, fixed_corotated), one ``model(F, mu, lam) -> tau``.
- :mod:`causalgs.sim.effects`: the registry of grid-update terms (``gravity``, ``linear_drag``, ``walls``).
- :mod:`causalgs.sim.reference`: the same substep in plain torch (tests only).
"""

from causalgs.sim.effects import REGISTRY, Effects
from causalgs.sim.materials import MODELS
from causalgs.sim.mpm import SimConfig, Simulator, momenta

__all__ = ["MODELS", "REGISTRY", "Effects", "SimConfig", "Simulator", "momenta"]
