"""The experiments' use of a ``realism`` section: self-ID under it, grid axes, and labels for summaries and figures.

The config block is :class:`~selfid_jax.experiments.common.schema.RealismConfig`
(``SelfIdRealismConfig`` where the experiment self-identifies); the model is
:mod:`selfid_jax.control.realism`. An experiment without the section runs the
ideal loop through the same calls (``realism=None``), exactly as before the
section existed.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np
import pandas as pd

from selfid_jax.control import realism as realism_lib
from selfid_jax.identify import algorithm as selfid

from .schema import REALISM_FIELDS, RealismConfig
from .specs import build_dynamic_arm

__all__ = ["add_realism_axis", "level_labels", "level_of", "plant", "realism_summary", "self_identify"]


def self_identify(system, key, q0, *, iters: int, eps, eps_rel, m_a, pose_noise, rot_noise,
                  realism: realism_lib.Realism | None = None, settle=1, max_latency: int = 0,
                  max_settle: int = 1, plant: realism_lib.Plant | None = None
                  ) -> tuple[selfid.SelfIDResult, jax.Array | None]:
    """Algorithm 1 on ``system`` from ``q0 (n,)``: ``(result, dropouts)``, ``result.env`` the final ``(n,)`` q.

    ``realism=None``: :func:`selfid_jax.identify.algorithm.run` (tracker noise
    ``pose_noise`` [m], ``rot_noise`` [rad] on every self-ID reading) and
    ``dropouts`` None. Otherwise each sample runs under ``realism``
    (:func:`selfid_jax.control.realism.self_id_sampler`: ``settle`` control
    steps between the command and the second reading, traced under the static
    ``max_settle``; the tracker's history sized by the static
    ``max_latency``), ``dropouts`` the ``()`` int32 count of tracker readings
    that dropped out (each rejects its sample: ``result.state.rejected``).
    The same estimator settings as ``run``, so :data:`~selfid_jax.control.realism.IDEAL`
    gives ``run``'s result bit for bit. ``plant``: the actuators' model
    (:func:`selfid_jax.control.realism.dynamic_plant` for an arm's physics;
    None, the kinematic servo), with ``realism`` only.
    """
    if realism is None:
        return selfid.run(system, key, q0, iters=iters, eps=eps, eps_rel=eps_rel, m_a=m_a, pose_noise=pose_noise,
                          rot_noise=rot_noise), None
    observe, env0 = realism_lib.self_id_sampler(system, realism, q0, pose_noise=pose_noise, rot_noise=rot_noise,
                                                settle=settle, max_settle=max_settle, max_latency=max_latency,
                                                plant=plant)
    res = selfid.self_identify(observe, key, m_a, eps, n_act=system.n_act, task_dim=system.task_dim, iters=iters,
                               env=env0, eps_rel=eps_rel)
    return res._replace(env=res.env.q), res.env.dropouts


def add_realism_axis(axes: dict[str, Any], realism: RealismConfig | None, before: str) -> dict[str, Any]:
    """``axes`` (the ``grid_table`` axes of an experiment) with a ``realism_level`` axis inserted before ``before``
    when there is a ``realism`` section (unchanged without)."""
    if realism is None:
        return axes
    out: dict[str, Any] = {}
    for name, values in axes.items():
        if name == before:
            out["realism_level"] = range(realism.n_levels())
        out[name] = values
    return out


def _fields(table: pd.DataFrame) -> list[str]:
    return [f for f in (*REALISM_FIELDS, "settle") if f in table.columns]


def level_of(table: pd.DataFrame) -> pd.Series:
    """Each row's ``realism_level`` (0 everywhere without a realism section), to group a results table by."""
    if "realism_level" in table.columns:
        return table["realism_level"]
    return pd.Series(np.zeros(len(table), int), index=table.index, name="realism_level")


def level_labels(table: pd.DataFrame) -> dict[int, str]:
    """``{realism_level: label}`` from a results table: the values that differ between levels (``"latency=1,
    noise_pos=0.0001"``), or the nonzero ones if only one level, or ``"ideal"``; ``{}`` without realism columns."""
    if "realism_level" not in table.columns:
        return {}
    fields = _fields(table)
    firsts = table.drop_duplicates("realism_level").sort_values("realism_level")
    varying = [f for f in fields if firsts[f].nunique() > 1]
    if not varying:
        varying = [f for f in fields if f != "settle" and np.any(firsts[f].to_numpy(float) != 0)]
    labels = {}
    for _, row in firsts.iterrows():
        text = ", ".join(f"{f}={row[f]:g}" for f in varying)
        labels[int(row["realism_level"])] = text or "ideal"
    return labels


def realism_summary(table: pd.DataFrame, level: int) -> dict[str, Any]:
    """The realism values of ``level`` (for summary.json), ``{name: value}``."""
    row = table[table["realism_level"] == level].iloc[0]
    return {f: (int(row[f]) if f in ("latency", "settle") else float(row[f])) for f in _fields(table)}


def plant(realism: RealismConfig | None, spec, system) -> realism_lib.Plant | None:
    """The actuators' model a ``realism`` section names: None for ``plant: servo`` (the kinematic servo of
    :func:`selfid_jax.control.realism.servo`) or no section; for ``plant: dynamic`` the arm of system ``spec``
    stepped in MJX (:func:`selfid_jax.control.realism.dynamic_plant`), ``period / timestep`` physics steps per
    control step. ``ValueError`` naming the problem (not an arm with position servos, a period that is not a
    multiple of the model's timestep, another actuator count than ``system``'s)."""
    if realism is None or realism.plant == "servo":
        return None
    from selfid_jax.systems.dynamic import substeps_for

    arm = build_dynamic_arm(spec, gravcomp=realism.gravcomp).with_servo(kp=realism.kp, kv=realism.kv)
    try:
        substeps = substeps_for(arm, realism.period[0])
    except ValueError as exc:
        raise ValueError(f"realism.period: {exc}") from None
    if abs(substeps * arm.timestep - realism.period[0]) > 1e-9 * max(realism.period[0], 1.0):
        raise ValueError(f"realism.period {realism.period[0]} s is not a whole number of the model's physics steps "
                         f"({arm.timestep} s); use e.g. {substeps * arm.timestep:g} s")
    out = realism_lib.dynamic_plant(arm, substeps)
    realism_lib.check_plant(out, system.n_act)
    return out
