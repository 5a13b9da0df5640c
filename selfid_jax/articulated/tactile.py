"""Simulated tactile pads: an ``R x C`` marker grid per pad, read in the gripper frame (seed 003 Eq. 2-3).

Model (stated, not a gel FEM): the gripper closes along its y axis on a
cylindrical handle bar of radius ``bar_radius`` whose axis is the gripper's z
axis; each pad's undeformed surface lies at ``|y| = bar_radius - squeeze``, so
the bar indents marker ``k`` (lateral offset ``x_k`` from the bar axis) by
``delta_k = max(0, sqrt(r^2 - x_k^2) - (r - squeeze))`` (0 where ``|x_k| >= r``).
Markers do not slip on the handle (the seed's Sec. 3.3 assumption): at step
``i`` a marker in contact sits at ``X_i X_1^-1 c_1`` where ``X = T_g^-1 T_h``
is the handle's pose in the gripper frame; its normal deformation becomes
``delta_k + n_k . (c_i - c_1)`` (``n_k`` the pad's inward normal). The active
set is Eq. 2: markers whose normal deformation is ``>= contact_eps`` now and
at the start (the pairs ``K_{1,i}``, Eq. 10). Readings get Gaussian noise of
sd ``marker_noise`` [m] on every coordinate.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

__all__ = ["Pads", "pads", "read"]


class Pads(NamedTuple):
    """Static marker layout of both pads (gripper frame), float arrays."""

    ref: np.ndarray  # (M, 3) marker positions at the initial grasp c_1 [m]
    normal: np.ndarray  # (M, 3) inward unit normal of each marker's pad
    delta0: np.ndarray  # (M,) initial normal deformation [m]


def pads(*, rows: int = 8, cols: int = 8, pitch: float = 0.0025, bar_radius: float = 0.006,
         squeeze: float = 0.001) -> Pads:
    """Two ``rows x cols`` grids (x: across the bar, ``cols``; z: along it, ``rows``) at ``y = +-surface``:
    ``M = 2 rows cols``."""
    if rows < 1 or cols < 1 or not pitch > 0 or not bar_radius > squeeze > 0:
        raise ValueError("pads need rows, cols >= 1, pitch > 0 and bar_radius > squeeze > 0")
    x = (np.arange(cols) - (cols - 1) / 2) * pitch
    z = (np.arange(rows) - (rows - 1) / 2) * pitch
    X, Z = np.meshgrid(x, z, indexing="xy")
    X, Z = X.ravel(), Z.ravel()
    surf = bar_radius - squeeze
    bar = np.sqrt(np.clip(bar_radius**2 - X**2, 0.0, None))
    delta = np.where(np.abs(X) < bar_radius, np.clip(bar - surf, 0.0, None), 0.0)
    refs, normals, deltas = [], [], []
    for side in (1.0, -1.0):
        refs.append(np.stack([X, side * (surf + delta), Z], axis=1))
        normals.append(np.tile([0.0, side, 0.0], (X.size, 1)))
        deltas.append(delta)
    return Pads(np.concatenate(refs), np.concatenate(normals), np.concatenate(deltas))


def read(pads_: Pads, X_rel: jaxlie.SE3, key, marker_noise, contact_eps):
    """Marker reading at in-hand pose change ``X_rel = X_i X_1^-1``: ``(cur (M, 3), mask (M,), delta (M,))``.

    ``marker_noise`` sd [m] on each coordinate; ``contact_eps`` the Eq. 2
    contact threshold [m]. ``mask`` = ``K_{1,i}``: in contact now and at the start. Markers out
    of contact are reported at their reference (the gel is at rest there).
    """
    ref = jnp.asarray(pads_.ref)
    moved = jax.vmap(X_rel.apply)(ref)
    delta = jnp.asarray(pads_.delta0) + jnp.sum(jnp.asarray(pads_.normal) * (moved - ref), axis=-1)
    start = jnp.asarray(pads_.delta0) >= contact_eps
    mask = start & (delta >= contact_eps)
    cur = jnp.where(start[:, None], moved, ref) + marker_noise * jax.random.normal(key, ref.shape, ref.dtype)
    return cur, mask, delta
