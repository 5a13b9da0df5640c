"""Simulated tactile pads: an ``R x C`` marker grid per pad, read in the gripper frame (seed 003 Eq. 2-3).

Model (stated, not a gel FEM): the gripper closes along its y axis on a
cylindrical handle bar of radius ``bar_radius`` whose axis is the gripper's z
axis; each pad's undeformed surface lies at ``|y| = bar_radius - squeeze``, so
the bar indents marker ``k`` (lateral offset ``x_k`` from the bar axis) by
``delta_k = max(0, sqrt(r^2 - x_k^2) - (r - squeeze))`` (0 where ``|x_k| >= r``).
Markers do not slip on the handle (the seed's Sec. 3.3 assumption): at step
``i`` a marker in contact sits at ``X_i X_1^-1 c_1`` where ``X = T_g^-1 T_h``
is the handle's pose in the gripper frame; its normal deformation becomes
``delta_k + n_k . (c_i - c_1)`` (``n_k`` the pad's inward normal). Readings get
Gaussian noise of sd ``marker_noise`` [m] on every coordinate, so a measured
deformation carries the noise's normal component. The active set is Eq. 2:
markers whose measured normal deformation is ``>= eps`` now and that were in
the initial contact set ``C_1`` (the pairs ``K_{1,i}``, Eq. 10).

The threshold ``eps`` (:func:`initial_contact`): a fixed ``contact_eps``, or
the seed's rule (Sec. 5.1: "we dynamically adjust the contact threshold
epsilon in Eq. 2 during each trial to the smallest value that yields exactly 9
contact points in the initial contact set"), :func:`paper_threshold` on the
first (noisy) reading. On these pads the rule is degenerate: a flat pad on a
cylindrical bar deforms only along x, so the initial deformations tie (32
markers at 0.868 mm at the default grasp) and only the reading noise decides
which 9 markers pass; the next readings, with fresh noise, keep each of them
with a probability of about 0.3 (docs/results/articulated.md measures the effect).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

__all__ = ["Pads", "initial_contact", "pads", "paper_threshold", "read"]


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


def paper_threshold(delta, n_points):
    """Seed 003 Sec. 5.1: the smallest Eq. 2 threshold leaving exactly ``n_points`` markers in contact: ``(eps, ok)``.

    ``delta (M,)`` measured normal deformations [m]; ``n_points`` () int, ``1 <=
    n_points < M`` (may be traced). With ``d_(1) >= d_(2) >= ...`` the sorted
    deformations, ``#{delta >= eps} = n_points`` exactly for ``d_(n+1) < eps <=
    d_(n)``, so the smallest such ``eps`` is the next float above ``d_(n+1)``.
    ``ok`` (bool scalar) is False when no threshold gives exactly ``n_points``
    (``d_(n) == d_(n+1)``, a tie); ``eps`` is then the same expression (fewer
    than ``n_points`` pass).
    """
    d = jnp.sort(delta)[::-1]
    n = jnp.asarray(n_points, jnp.int32)
    above, below = d[n - 1], d[n]
    return jnp.nextafter(below, jnp.asarray(jnp.inf, d.dtype)), above > below


def initial_contact(pads_: Pads, key, marker_noise, contact_eps, contact_points):
    """The initial reading ``C_1``: ``(eps, start (M,) bool, ok)`` (all traceable).

    ``contact_points`` () int: 0 for the fixed threshold ``contact_eps`` [m];
    ``> 0`` for the seed's rule (:func:`paper_threshold` on the deformations
    measured at the grasp, noise of sd ``marker_noise`` [m] included: a real
    sensor applies it to its reading). ``start``: markers whose measured
    deformation is ``>= eps``; ``ok`` False when the rule met a tie.
    """
    noise = marker_noise * jax.random.normal(key, pads_.ref.shape, jnp.result_type(float))
    measured = jnp.asarray(pads_.delta0) + jnp.sum(jnp.asarray(pads_.normal) * noise, axis=-1)
    use = jnp.asarray(contact_points) > 0
    eps_rule, ok = paper_threshold(measured, jnp.maximum(jnp.asarray(contact_points), 1))
    eps = jnp.where(use, eps_rule, contact_eps)
    return eps, measured >= eps, jnp.where(use, ok, True)


def read(pads_: Pads, X_rel: jaxlie.SE3, key, marker_noise, contact_eps, start=None):
    """Marker reading at in-hand pose change ``X_rel = X_i X_1^-1``: ``(cur (M, 3), mask (M,), delta (M,))``.

    ``marker_noise`` sd [m] on each coordinate; ``contact_eps`` the Eq. 2
    contact threshold [m]; ``start (M,)`` bool the initial contact set ``C_1``
    (default: the noise-free ``delta0 >= contact_eps``). ``delta`` the measured
    normal deformation (noise included); ``mask`` = ``K_{1,i}``: ``delta >=
    contact_eps`` now and in ``C_1``. Markers outside ``C_1`` are reported at
    their reference (the gel is at rest there).
    """
    ref = jnp.asarray(pads_.ref)
    normal = jnp.asarray(pads_.normal)
    moved = jax.vmap(X_rel.apply)(ref)
    noise = marker_noise * jax.random.normal(key, ref.shape, ref.dtype)
    delta = jnp.asarray(pads_.delta0) + jnp.sum(normal * (moved - ref), axis=-1) + jnp.sum(normal * noise, axis=-1)
    start = jnp.asarray(pads_.delta0) >= contact_eps if start is None else start
    mask = start & (delta >= contact_eps)
    cur = jnp.where(start[:, None], moved, ref) + noise
    return cur, mask, delta
