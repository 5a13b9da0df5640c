"""The E-KM rows of the estimation ablation (issue 16): config schema, validation, static groups and their rollouts.

An E-KM row (``method: ekm``, :mod:`selfid_jax.baselines.ekm`) is a nominal
kinematic model with wrong parameters (``nominal: {scale, offset}``, see
:func:`~selfid_jax.baselines.ekm.nominal_system`) corrected by a Sparse Online
GP learned from the same self-ID stream as every other method, and followed by
its own Eq. 10-11 QP controller (:func:`~selfid_jax.baselines.ekm.follow`),
``options.mode``: ``fixed`` (GP learned during self-ID only) or ``online``
(also from every control step). The other options go to
:func:`~selfid_jax.baselines.ekm.model` (formulation, symmetric, GP settings).

E-KM rows that share the static settings (formulation, mirror, mode) form one
:class:`EKMGroup`: their models (different nominal errors, GP settings) are
stacked and every (row, checkpoint) of the group is followed by ONE vmapped
rollout, as the fixed estimates of the model-free methods are.

The GP capacity is ``max(64, 2 x the largest checkpoint)``: the mirrored
self-ID samples are never pruned (online mode then prunes as it learns from
control steps). ``converged_at`` is the Sec. IV-D test on ``pinv`` of the
control Jacobian linearised at the start configuration after each sample.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Literal, NamedTuple, get_args

import jax
import jax.numpy as jnp
from pydantic import BaseModel

from selfid_jax import baselines
from selfid_jax.baselines import ekm
from selfid_jax.baselines.base import check_choice
from selfid_jax.baselines.registry import MODEL_BASED
from selfid_jax.identify import estimator
from selfid_jax.math.linalg import pseudo_inverse
from selfid_jax.systems import System

__all__ = ["NominalSpec", "EKMGroup", "check_methods", "capacity", "groups", "rollouts"]

RESERVED = ("nominal", "q0")  # given by the ablation, not by options


class NominalSpec(BaseModel):
    """The nominal model of an E-KM row: the true system with link lengths scaled and joints offset."""

    model_config = dict(extra="forbid", frozen=True, allow_inf_nan=False)

    scale: float | list[float] = 1.0  # length factors: () or the system's params / ChainModel body count
    offset: float | list[float] = 0.0  # joint offsets [rad]: () or (n_act,)


class EKMGroup(NamedTuple):
    """E-KM rows with the same static settings: one stacked model, one rollout loop."""

    rows: tuple[int, ...]  # method indices (config order) of the rows in this group
    models: Any  # ekm.EKMModel with leading axis len(rows)
    mode: Literal["fixed", "online"]
    capacity: int  # GP basis size


def check_methods(methods, system_spec) -> None:
    """Validate E-KM rows before any compute: ``nominal`` required iff the method is model-based, with shapes
    the system takes; errors name ``methods[i].nominal`` / ``.scale`` / ``.offset`` / ``.options``."""
    system = None
    for i, spec in enumerate(methods):
        where = f"methods[{i}] ({spec.name!r})"
        if spec.method not in MODEL_BASED:
            if spec.nominal is not None:
                raise ValueError(f"{where}.nominal: only model-based methods ({', '.join(MODEL_BASED)}) take a "
                                 f"nominal model, not {spec.method!r}")
            continue
        if spec.nominal is None:
            raise ValueError(f"{where}.nominal: required for method {spec.method!r} (e.g. nominal: "
                             "{scale: [1.2, 0.8], offset: [0.1, -0.1]})")
        bad = sorted(set(spec.options) & set(RESERVED))
        if bad:
            raise ValueError(f"{where}.options: {', '.join(bad)} are set by the ablation (use nominal:), not options")
        if system is None:
            from .specs import build_system

            system = build_system(system_spec)
        for key in ("scale", "offset"):
            try:
                ekm.nominal_system(system, **{key: getattr(spec.nominal, key)})
            except ValueError as e:
                raise ValueError(f"{where}.nominal.{key}: {e}") from None


def capacity(iters: int) -> int:
    """GP capacity of every E-KM row: ``2 x iters`` mirrored self-ID samples fit, at least 64."""
    return max(64, 2 * iters)


def groups(system: System, methods, iters: int) -> tuple[EKMGroup, ...]:
    """The :class:`EKMGroup` s of the E-KM rows of ``methods`` (MethodSpecs, config order) on ``system``."""
    by_key: dict[tuple, list[tuple[int, ekm.EKMModel]]] = {}
    for i, spec in enumerate(methods):
        if spec.method not in MODEL_BASED:
            continue
        opts = dict(spec.options)
        mode = check_choice("ekm", "mode", opts.pop("mode", "fixed"), ekm.MODES)
        nominal = ekm.nominal_system(system, **spec.nominal.model_dump())
        mdl = ekm.model(nominal, **opts)
        fl = jnp.result_type(float)  # the GP settings: python floats -> stackable arrays
        mdl = dataclasses.replace(mdl, length_q=jnp.asarray(mdl.length_q, fl), length_da=jnp.asarray(mdl.length_da, fl),
                                  signal=jnp.asarray(mdl.signal, fl), noise=jnp.asarray(mdl.noise, fl),
                                  novelty_tol=jnp.asarray(mdl.novelty_tol, fl))
        by_key.setdefault((mdl.formulation, mdl.symmetric, mode), []).append((i, mdl))
    out = []
    for (_, _, mode), members in by_key.items():
        models = jax.tree.map(lambda *x: jnp.stack(x), *(m for _, m in members))
        out.append(EKMGroup(tuple(i for i, _ in members), models, mode, capacity(iters)))
    return tuple(out)


def rollouts(group: EKMGroup, system: System, path, q0, controller, sid, checkpoints, steps: int, eps, eps_rel,
             accepted):
    """One group on one self-ID stream: ``(FollowResult (G, C), converged_at (G,))``.

    Each row's GP folds the stream (:func:`ekm.update`, dead-reckoned from
    ``q0``); its states at the checkpoints are followed on the true
    ``system`` by one vmapped :func:`ekm.follow` over all ``G x C`` (row,
    checkpoint) pairs.
    """
    G, C = len(group.rows), checkpoints.shape[0]

    def fold(mdl):
        def body(s, x):
            s = ekm.update(mdl, s, *x)
            return s, (s, pseudo_inverse(ekm.linearise(mdl, s, s.q0)[0]))

        _, (states, ests) = jax.lax.scan(body, ekm.init(mdl, q0, capacity=group.capacity), (sid.dtheta, sid.V))
        conv = estimator.convergence_iteration(ests, eps, eps_rel, accepted=accepted)
        return jax.tree.map(lambda a: a[checkpoints], states), conv

    at, converged = jax.vmap(fold)(group.models)  # states (G, C, ...), (G,)
    flat = lambda a: a.reshape((G * C,) + a.shape[2:])
    models = jax.tree.map(lambda a: jnp.repeat(a, C, axis=0), group.models)
    res = jax.vmap(lambda m, s: ekm.follow(m, s, system, path, controller, mode=group.mode, steps=steps)[0])(
        models, jax.tree.map(flat, at))
    return jax.tree.map(lambda a: a.reshape((G, C) + a.shape[1:]), res), converged


def is_model_based(method: str) -> bool:
    return method in MODEL_BASED


METHOD_CHOICES = baselines.METHOD_NAMES + tuple(MODEL_BASED)
MethodName = Literal["ours", "direct", "sign_true_mag", "true", "broyden", "rls", "kalman", "particle", "ekm"]
"""A ``method`` of the ablation config: :data:`METHOD_CHOICES` written out (a type checker needs the names)."""
if get_args(MethodName) != METHOD_CHOICES:
    raise RuntimeError(f"MethodName {get_args(MethodName)} is out of date: the methods are {METHOD_CHOICES}")
