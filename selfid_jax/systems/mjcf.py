"""MJCF systems: :func:`from_mjcf` builds a :class:`System` from a MuJoCo model, its actuators and a site.

The actuation space is the model's actuators (the ``q -> qpos`` map of
:mod:`selfid_jax.systems.actuation`); the pose maps are those of
:mod:`selfid_jax.systems.kinematics` (:class:`ChainSitePose`, a plain-JAX
walk of the joint chain, or :class:`MjxSitePose`, ``mjx.kinematics``).
Only kinematics are used, so any integrator, solver or option loads.
"""

from __future__ import annotations

import os
import warnings

import numpy as np

from selfid_jax.systems.actuation import build_actuation
from selfid_jax.systems.kinematics import (
    ChainModel,
    ChainSitePose,
    MjxSitePose,
    chain_site_pose,
    kinematic_mjx_model,
)
from selfid_jax.systems.system import System, make_system
from selfid_jax.systems.validation import Limits, Values, check_task_dim, vector

__all__ = ["from_mjcf", "POM_SITE", "resolve_home", "MjxSitePose", "ChainSitePose", "ChainModel", "HINGE_HALF_WIDTH",
           "RANGE_FRACTION"]

#: Default sampling half-width (rad) around home for actuators that move hinges only.
HINGE_HALF_WIDTH = 0.5
#: Default sampling half-width of other actuators (slides, tendons), as a fraction of their finite range.
RANGE_FRACTION = 0.25


POM_SITE = "selfid_jax_pom"
"""Name of the site :func:`from_mjcf` adds for a point of manipulation given as ``body`` + ``offset``."""


def _is_urdf(path_or_model) -> bool:
    if isinstance(path_or_model, os.PathLike) or (isinstance(path_or_model, str)
                                                  and not path_or_model.lstrip().startswith("<")):
        return os.fspath(path_or_model).lower().endswith(".urdf")
    return isinstance(path_or_model, str) and path_or_model.lstrip().startswith(("<robot", "<?xml")) \
        and "<robot" in path_or_model[:2000]


def _load_mjmodel(path_or_model, *, body: str | None = None, offset=None):
    """``(mujoco.MjModel, label)`` of a path, an XML string (MJCF or URDF) or an ``MjModel``.

    A URDF keeps its fixed-joint links as bodies (``fusestatic`` off), so a tool link can be the POM's ``body``.
    With ``body``, a site :data:`POM_SITE` is added to that body at ``offset`` (m, body frame) before compiling.
    """
    import mujoco

    if isinstance(path_or_model, mujoco.MjModel):
        if body is not None:
            raise ValueError("body= needs the model's file or XML string (a compiled mujoco.MjModel cannot gain a "
                             "site); pass the path, or a site= the model has")
        return path_or_model, "<MjModel>"
    is_file = isinstance(path_or_model, (str, os.PathLike)) and not str(path_or_model).lstrip().startswith("<")
    if not is_file and not isinstance(path_or_model, str):
        raise ValueError(f"path_or_model must be a path, an XML string or a mujoco.MjModel, got {type(path_or_model)}")
    label = os.fspath(path_or_model) if is_file else "<xml string>"
    kind = "URDF" if _is_urdf(path_or_model) else "MJCF"
    try:
        if kind == "MJCF" and body is None:
            if is_file:
                return mujoco.MjModel.from_xml_path(label), label
            return mujoco.MjModel.from_xml_string(path_or_model), label
        spec = mujoco.MjSpec.from_file(label) if is_file else mujoco.MjSpec.from_string(path_or_model)
        if kind == "URDF":
            spec.compiler.fusestatic = False  # keep fixed-joint links (a tool flange) as bodies
    except Exception as e:
        what = f"{kind} file {label!r}" if is_file else f"{kind} XML string"
        raise ValueError(f"could not load {what}: {e}") from e
    if body is not None:
        b = spec.body(str(body))
        if b is None:
            names = [x.name for x in spec.bodies if x.name and x.name != "world"]
            raise ValueError(f"body {body!r} not found in {kind} {label}; bodies are {names}")
        b.add_site(name=POM_SITE, pos=[float(v) for v in offset])
    try:
        return spec.compile(), label
    except Exception as e:
        raise ValueError(f"could not compile {kind} {label}: {e}") from e


def _keyframe_home(mj, act, key: str, label: str) -> np.ndarray:
    """Actuator coordinates ``(n,)`` of keyframe ``key``'s ``qpos``."""
    import mujoco

    k = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_KEY, str(key))
    if k < 0:
        names = [mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_KEY, i) for i in range(mj.nkey)]
        raise ValueError(f"home: keyframe {key!r} not found in {label}; keyframes are {names}")
    return act.lengths @ np.asarray(mj.key_qpos[k], np.float64)


def resolve_home(mj, act, home, q_low, q_high, label: str) -> tuple[np.ndarray, str]:
    """``(home (n,), where it came from)``: ``home`` as given, keyframe ``home["keyframe"]``, else the model's
    ``home`` keyframe if it has one, else ``qpos0`` (clipped into the limits with a warning naming each actuator)."""
    import mujoco

    n = len(act.qmap.names)
    if isinstance(home, dict):
        if set(home) != {"keyframe"}:
            raise ValueError(f"home: a vector of {n} actuator positions or {{'keyframe': NAME}}, got {home!r}")
        source = f"keyframe {home['keyframe']!r}"
        home = _keyframe_home(mj, act, home["keyframe"], label)
    elif home is None and mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_KEY, "home") >= 0:
        source, home = "keyframe 'home'", _keyframe_home(mj, act, "home", label)
    elif home is None:
        outside = [f"{nm!r} at {h:.6g} outside [{lo:.6g}, {hi:.6g}]" for nm, h, lo, hi
                   in zip(act.qmap.names, act.home, q_low, q_high) if not lo <= h <= hi]
        if outside:
            warnings.warn(f"{label}: qpos0 puts actuator {'; '.join(outside)}; home is clipped into the limits "
                          "(pass home=[...] or add a 'home' keyframe)", stacklevel=3)
        return np.clip(act.home, q_low, q_high), "qpos0"
    else:
        source = "home"
    home = vector("home", home, n)
    if np.any(home < q_low) or np.any(home > q_high):
        raise ValueError(f"home ({source}) {home} must lie inside the limits [{q_low}, {q_high}]")
    return home, source


def _sampling_box(act, q_low, q_high, home, sample_half_width):
    """``(low, high)`` ``(n,)``: ``home +- half-width`` clipped to ``[q_low, q_high]`` (see :func:`from_mjcf`)."""
    n = len(act.qmap.names)
    if sample_half_width is None:
        width = np.where(act.hinge_only, HINGE_HALF_WIDTH, RANGE_FRACTION * (q_high - q_low))
        bad = [f"{nm!r} ({d})" for nm, d, w in zip(act.qmap.names, act.descs, width) if not np.isfinite(w)]
        if bad:
            raise ValueError(
                f"actuators {', '.join(bad)} move slides or tendons and have no finite range: pass "
                "sample_half_width (actuator units) or sample_low/sample_high"
            )
    else:
        width = vector("sample_half_width", sample_half_width, n)
        if not np.all((width > 0) & np.isfinite(width)):
            raise ValueError(f"sample_half_width must be positive and finite, got {width}")
    return np.maximum(q_low, home - width), np.minimum(q_high, home + width)


def from_mjcf(
    path_or_model,
    site: str | None = None,
    *,
    body: str | None = None,
    offset: Values = (0.0, 0.0, 0.0),
    actuators=None,
    joints_fixed=None,
    task_dim: int,
    m_a: Values,
    fk: str = "chain",
    home: Values | dict | None = None,
    sample_half_width: Values | None = None,
    dq_max: Values = 0.1,
    q_low: Values | None = None,
    q_high: Values | None = None,
    sample_low: Values | None = None,
    sample_high: Values | None = None,
    min_sigma: float = 1e-3,
    name: str | None = None,
) -> System:
    """A :class:`System` from an MJCF or URDF model: actuator coordinates ``q (n_act,)`` -> pose of the POM.

    The point of manipulation (POM) is a site of the model (``site``) or a
    point of a body (``body``, at ``offset`` metres in the body frame; a site
    :data:`POM_SITE` is added there), so a model without sites needs no edits.
    A URDF loads directly; its fixed-joint links (a tool flange) stay bodies,
    and, having no actuators, it is used with ``actuators="joints"``.

    Actuation (:func:`~selfid_jax.systems.actuation.build_actuation`): ``q_i``
    is actuator ``i``'s transmission length without gear (rad / m): its joint's
    ``qpos`` for a joint transmission, its fixed tendon's length
    ``sum_k coef_k qpos_k`` for a tendon transmission. ``qpos(q)`` is the
    least-norm joint motion from ``qpos0`` (``joints_fixed`` applied) meeting
    the actuator lengths and the active linear joint/tendon equalities: a
    tendon alone moves joint ``k`` by ``coef_k (q - L0) / sum coef^2``, an
    equality follower follows its driver, every other joint stays at
    ``qpos0``/``joints_fixed``. Free and ball joints off the site's chain stay
    at ``qpos0``; on the chain they are an error. Connect/weld/distance
    equalities are ignored. ``System.jacobian`` is ``d task / d q`` (the joint
    geometric Jacobian times the static map ``A = d qpos / d q``).

    Limits (default ``q_low``/``q_high``): the intersection of the ranges of
    the limited joints an actuator moves, its tendon's range and, for position
    servos (fixed gain, affine bias with ``biasprm[1] < 0``), its ``ctrlrange``
    mapped to a length; +-inf where none applies (a motor's ``ctrlrange`` is a
    force and is not used).

    Sampling box (default): ``home +- sample_half_width`` clipped to the
    limits, ``home`` = the model's ``home`` keyframe if it has one, else
    ``qpos0`` in actuator coordinates (clipped to the limits, with a warning
    naming each actuator outside them), half-width :data:`HINGE_HALF_WIDTH` = 0.5 rad for actuators moving
    hinges only, else :data:`RANGE_FRACTION` = 1/4 of the actuator's range.

    Only kinematics are used: ``fk="chain"`` stores just the arrays the walk
    needs (:class:`ChainModel`) and never calls ``mjx.put_model``; ``fk="mjx"``
    puts a kinematics-only copy (:func:`~selfid_jax.systems.kinematics.kinematic_mjx_model`:
    Euler integrator, Newton solver, pyramidal cones, dense Jacobian, no enable
    flags, fluid or contacts, unsupported types replaced), so any integrator
    (``implicit``...), solver or option loads.

    Args:
      path_or_model: MJCF or URDF file path (``.urdf``), XML string, or a ``mujoco.MjModel``.
      site: name of the POM site; give exactly one of ``site`` and ``body``.
      body: name of the POM's body (needs a path or XML string, not an ``MjModel``).
      offset: ``(3,)`` POM position in ``body``'s frame [m].
      actuators: None (all actuators with a joint or fixed-tendon
        transmission; others skipped with a warning), a list of actuator names
        (in ``q`` order), or ``"joints"`` (every hinge/slide joint, ``q = qpos``).
      joints_fixed: ``{joint name: value}`` (rad / m) for undriven hinge/slide joints.
      task_dim: 2, 3 or 6.
      m_a: safe self-ID magnitude, scalar or ``(n_act,)`` (actuator units).
      fk: ``"chain"`` (default, several times faster) or ``"mjx"``; equal to rounding.
      home: ``(n_act,)`` centre of the default sampling box, or ``{"keyframe": name}``.
      sample_half_width: scalar or ``(n_act,)`` half-width of the default box.
      dq_max: per-step actuator limit, scalar or ``(n_act,)``.
      q_low, q_high: override the limits, scalar or ``(n_act,)``.
      sample_low, sample_high: explicit sampling box (replaces the default).
      min_sigma: singularity threshold for ``sample_configs``.
      name: label (default: the file's base name, or ``"mjcf"``).

    Returns:
      A :class:`System`; ``params`` is a :class:`ChainModel` (``fk="chain"``) or
      an ``mjx.Model``; ``system.pose_fn.qmap`` holds the actuator names and map.

    Raises:
      ValueError: naming the site, body, keyframe, actuator, joint or argument at fault.
    """
    import mujoco

    if fk not in ("chain", "mjx"):
        raise ValueError(f"fk must be 'mjx' or 'chain', got {fk!r}")
    check_task_dim(task_dim)
    if (site is None) == (body is None):
        raise ValueError("give the point of manipulation as site='name' or as body='name' (with offset=(x, y, z) "
                         f"in the body frame), exactly one of them; got site={site!r}, body={body!r}")
    if body is not None:
        if not isinstance(body, str):
            raise ValueError(f"body must be a body name (str), got {body!r}")
        offset = vector("offset", offset, 3)
        if not np.all(np.isfinite(offset)):
            raise ValueError(f"offset must be finite, got {offset}")
    mj, label = _load_mjmodel(path_or_model, body=body, offset=offset)
    if body is not None:
        site = POM_SITE
    if not isinstance(site, str):
        raise ValueError(f"site must be a site name (str), got {site!r}")
    site_id = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_SITE, site)
    if site_id < 0:
        names = [mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_SITE, i) for i in range(mj.nsite)]
        bodies = [mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_BODY, i) for i in range(1, mj.nbody)]
        raise ValueError(f"site {site!r} not found in {label}; sites are {names}; or give the POM as a body and "
                         f"an offset (body='name', offset=(x, y, z)); bodies are {bodies}")

    act = build_actuation(mj, actuators=actuators, joints_fixed=joints_fixed, label=label)
    chain = chain_site_pose(mj, int(site_id), site, act.qmap)  # also rejects free/ball joints on the chain
    n = len(act.qmap.names)
    try:
        q_low = vector("q_low", act.low if q_low is None else q_low, n)
        q_high = vector("q_high", act.high if q_high is None else q_high, n)
        if sample_low is None or sample_high is None:
            home, _ = resolve_home(mj, act, home, q_low, q_high, label)
            box_low, box_high = _sampling_box(act, q_low, q_high, home, sample_half_width)
            sample_low = box_low if sample_low is None else sample_low
            sample_high = box_high if sample_high is None else sample_high
        pose_fn: ChainSitePose | MjxSitePose
        if fk == "chain":
            pose_fn, params = chain, ChainModel.from_mjmodel(mj)
        else:
            pose_fn, params = MjxSitePose(int(site_id), act.qmap), kinematic_mjx_model(mj, label)
        if name is None:
            name = os.path.splitext(os.path.basename(label))[0] if label[0] != "<" else "mjcf"
        return make_system(
            name=name,
            params=params,
            pose_fn=pose_fn,
            has_rotation=True,
            limits=Limits(n, task_dim, q_low, q_high, dq_max, m_a, sample_low, sample_high, min_sigma),
        )
    except ValueError as e:
        raise ValueError(f"{e} [MJCF {label}: {n} actuators {list(act.qmap.names)}]") from e
