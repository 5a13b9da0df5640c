"""Numeric foundations: small dense linear algebra, SO(3) helpers and pose differences, eager argument checks.

The bottom layer: it imports nothing else of ``selfid_jax``.
"""

from selfid_jax.math import checks, geometry, kernels, linalg

__all__ = ["checks", "geometry", "kernels", "linalg"]
