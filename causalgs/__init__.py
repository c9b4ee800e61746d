"""CausalGS: learn the physics of a dynamic 3D scene from multi-view video and predict its future.

Importing the package never initialises Taichi; call :func:`causalgs._ti.init` (the command line does) first.
"""

from causalgs.errors import CausalGSError, DataError

__version__ = "0.1.0"
__all__ = ["CausalGSError", "DataError", "__version__"]
