"""Numeric foundations: small PSD linear algebra, SE(3) pose differences, argument checks, XLA-CPU kernels.

The bottom layer: it imports nothing else of ``selfid_jax``.
"""
