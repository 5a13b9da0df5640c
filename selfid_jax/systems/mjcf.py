"""MJCF systems: pose maps of an MJCF site and the :func:`from_mjcf` builder.

Two pose maps read the same ``mjx.Model`` (stored in ``System.params``):
:class:`MjxSitePose` runs ``mjx.kinematics``; :class:`ChainSitePose` walks the
joint chain from the world to the site in plain JAX and also gives the
world-frame site Jacobian ``(6, nq)`` from the same walk (the hot path of
UR5e rollouts). Both map ``q`` (``(nq,)``, rad / m, ``q = qpos``) to
``(p (3,), R (3, 3))`` in the model's length unit.
"""

from __future__ import annotations

import dataclasses
import os

import jax.numpy as jnp
import jaxlie
import numpy as np

from selfid_jax import geometry
from selfid_jax.systems.system import System, make_system
from selfid_jax.systems.validation import vector

__all__ = ["from_mjcf", "MjxSitePose", "ChainSitePose"]


def _mjx():
    """``mujoco.mjx``, imported with its stdout notices about the optional Warp backend silenced."""
    import contextlib
    import io

    with contextlib.redirect_stdout(io.StringIO()):
        from mujoco import mjx
    return mjx


@dataclasses.dataclass(frozen=True)
class MjxSitePose:
    """Pose map of an MJCF site by ``mjx.kinematics``: ``(mjx.Model, q) -> (site_xpos, site_xmat)``.

    ``q`` is written into ``qpos`` (hinge/slide joints only, so ``q = qpos``).
    Hashable by value, so systems rebuilt from the same file share compiled
    code.
    """

    site_id: int

    def __call__(self, model, q):
        mjx = _mjx()

        d = mjx.make_data(model)
        d = d.replace(qpos=jnp.asarray(q, dtype=d.qpos.dtype))
        d = mjx.kinematics(model, d)
        return d.site_xpos[self.site_id], d.site_xmat[self.site_id].reshape(3, 3)


@dataclasses.dataclass(frozen=True)
class ChainSitePose:
    """Pose map of an MJCF site by a plain-JAX product of joint transforms.

    Walks only the bodies from the world to the site's body (static indices),
    reading ``body_pos``, ``body_quat``, ``jnt_pos``, ``jnt_axis``, ``qpos0``,
    ``site_pos`` and ``site_quat`` from the ``mjx.Model`` in ``params`` (so it
    follows the MJCF, including a swept/batched model), with rotation matrices
    instead of MJX's quaternions and without computing every body, geom and
    site. Same convention as MuJoCo: a hinge rotates about its anchor by
    ``qpos - qpos0``; a slide translates by ``qpos - qpos0``. The constant
    body rotations and all joint rotations are built in one vectorised step
    each, which keeps tracing and compilation short.

    Attributes:
      site_id: site index.
      bodies: body ids from the world's child down to the site's body.
      joints: per body, tuple of ``(joint id, qpos address, is_hinge)``.
    """

    site_id: int
    bodies: tuple[int, ...]
    joints: tuple[tuple[tuple[int, int, bool], ...], ...]

    def __call__(self, model, q):
        p, R, _ = self._walk(model, q)
        return p, R

    def jacobian(self, model, q):
        """Site Jacobian ``(6, nq)`` in the world frame: rows ``[dp/dq; omega/dq]`` (as ``mj_jacSite``).

        Hinge column ``i``: ``[a_i x (p - c_i); a_i]`` with world axis ``a_i`` and
        anchor ``c_i``; slide column: ``[a_i; 0]``. Computed from the same walk as
        the pose, so it costs about one forward-kinematics pass instead of the
        ``nq + 1`` of ``jax.jacfwd``.
        """
        return self.pose_and_jacobian(model, q)[1]

    def pose_and_jacobian(self, model, q):
        """``((p, R), J (6, nq))`` from one walk: the pose of :meth:`__call__` and :meth:`jacobian`."""
        p, R, joints = self._walk(model, q)
        nq = jnp.shape(q)[-1]
        cols = [jnp.zeros(6, p.dtype)] * nq
        for adr, is_hinge, axis_w, anchor in joints:
            if is_hinge:
                cols[adr] = jnp.concatenate([jnp.cross(axis_w, p - anchor), axis_w])
            else:
                cols[adr] = jnp.concatenate([axis_w, jnp.zeros(3, p.dtype)])
        return (p, R), jnp.stack(cols, axis=1)

    def _walk(self, model, q):
        """World pose of the site and, per joint, ``(qpos address, is_hinge, world axis, world anchor)``."""
        q = jnp.asarray(q)
        dtype = jnp.result_type(q, model.body_pos)
        bodies = np.asarray(self.bodies, dtype=np.int32)
        flat = [jt for jnts in self.joints for jt in jnts]
        jid = np.asarray([j for j, _, _ in flat], dtype=np.int32)
        adr = np.asarray([a for _, a, _ in flat], dtype=np.int32)

        body_p = model.body_pos[bodies].astype(dtype)  # (nb, 3)
        body_R = jaxlie.SO3(model.body_quat[bodies].astype(dtype)).as_matrix()  # (nb, 3, 3); quats (w, x, y, z)
        if len(flat):
            angle = (q[adr] - model.qpos0[adr]).astype(dtype)  # (nj,)
            axis = model.jnt_axis[jid].astype(dtype)  # (nj, 3)
            jpos = model.jnt_pos[jid].astype(dtype)  # (nj, 3)
            k = geometry.hat(axis)
            eye = jnp.broadcast_to(jnp.eye(3, dtype=dtype), k.shape)
            # Rodrigues for unit axes (MuJoCo normalises jnt_axis): smooth, no division. Kept over
            # geometry.so3_exp (jaxlie): that costs ~1.5x in this walk and ~5-10% in rollout compile time.
            joint_R = eye + jnp.sin(angle)[:, None, None] * k + (1.0 - jnp.cos(angle))[:, None, None] * (k @ k)

        pos = jnp.zeros(3, dtype)
        rot = jnp.eye(3, dtype=dtype)
        joints = []
        i = 0
        for b, jnts in enumerate(self.joints):
            pos = pos + rot @ body_p[b]
            rot = rot @ body_R[b]
            for _, qadr, is_hinge in jnts:
                axis_w = rot @ axis[i]
                if is_hinge:
                    anchor = pos + rot @ jpos[i]
                    rot = rot @ joint_R[i]
                    pos = anchor - rot @ jpos[i]
                    joints.append((qadr, True, axis_w, anchor))
                else:
                    pos = pos + axis_w * angle[i]
                    joints.append((qadr, False, axis_w, None))
                i += 1
        p = pos + rot @ model.site_pos[self.site_id].astype(dtype)
        R = rot @ jaxlie.SO3(model.site_quat[self.site_id].astype(dtype)).as_matrix()
        return p, R, joints


def _load_mjmodel(path_or_xml):
    import mujoco

    if isinstance(path_or_xml, mujoco.MjModel):
        return path_or_xml, "<MjModel>"
    if isinstance(path_or_xml, (str, os.PathLike)) and not str(path_or_xml).lstrip().startswith("<"):
        label = os.fspath(path_or_xml)
        try:
            return mujoco.MjModel.from_xml_path(label), label
        except Exception as e:  # noqa: BLE001 - mujoco raises ValueError/Exception
            raise ValueError(f"could not load MJCF file {label!r}: {e}") from e
    if isinstance(path_or_xml, str):
        try:
            return mujoco.MjModel.from_xml_string(path_or_xml), "<xml string>"
        except Exception as e:  # noqa: BLE001
            raise ValueError(f"could not parse MJCF XML string: {e}") from e
    raise ValueError(f"path_or_xml must be a path, an XML string or a mujoco.MjModel, got {type(path_or_xml)}")


def from_mjcf(
    path_or_xml,
    site: str,
    *,
    task_dim: int,
    m_a,
    dq_max=0.1,
    q_low=None,
    q_high=None,
    sample_low=None,
    sample_high=None,
    min_sigma: float = 1e-3,
    fk: str = "mjx",
    name: str | None = None,
) -> System:
    """Build a :class:`System` from an MJCF model and the name of the POM site.

    The actuators are the model's joints, which must all be hinge or slide
    joints (``q = qpos``, ``n_act = nq``). Joint limits come from
    ``jnt_range`` for limited joints, else +-inf (override with
    ``q_low``/``q_high``); the sampling box defaults to the limits, with
    ``[-pi, pi]`` for unlimited hinges (unlimited slides need an explicit box).

    The ``mjx.Model`` is stored in ``params`` as a traced pytree: MJX marks its
    ``jax.Array`` fields as data and its ints/numpy arrays/enums (``nq``,
    ``jnt_type``, ``body_parentid``...) as hashable static metadata, so the
    whole ``System`` passes through ``jit``/``vmap`` (checked with MJX 3.17),
    and a sweep can batch model fields (e.g. ``body_pos``) with ``in_axes``.

    Args:
      path_or_xml: MJCF file path, XML string, or a ``mujoco.MjModel``.
      site: name of the POM site.
      task_dim: 2, 3 or 6.
      m_a: safe self-ID magnitude (scalar, rad / m).
      dq_max: per-step actuator limit, scalar or ``(nq,)``.
      q_low, q_high: override the limits from the file.
      sample_low, sample_high: sampling box (default: the limits).
      min_sigma: singularity threshold for ``sample_configs``.
      fk: ``"mjx"`` (``mjx.kinematics``, reads ``site_xpos``/``site_xmat``) or
        ``"chain"`` (:class:`ChainSitePose`, the same kinematics as a plain-JAX
        joint chain, faster; tested equal to ``"mjx"``).
      name: label (default: the model's name).

    Returns:
      A :class:`System` whose ``params`` is the ``mjx.Model``.
    """
    import mujoco
    mjx = _mjx()

    mj, label = _load_mjmodel(path_or_xml)
    if not isinstance(site, str):
        raise ValueError(f"site must be a site name (str), got {site!r}")
    site_id = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_SITE, site)
    if site_id < 0:
        names = [mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_SITE, i) for i in range(mj.nsite)]
        raise ValueError(f"site {site!r} not found in MJCF {label}; sites are {names}")
    hinge, slide = int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)
    bad = [
        (mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_JOINT, j), int(t))
        for j, t in enumerate(mj.jnt_type)
        if int(t) not in (hinge, slide)
    ]
    if bad or mj.njnt == 0:
        raise ValueError(f"MJCF {label}: every joint must be a hinge or slide (one actuator per joint); bad: {bad}")
    n = int(mj.nq)

    limited = np.asarray(mj.jnt_limited, bool)
    rng = np.asarray(mj.jnt_range, np.float64)
    lo = np.where(limited, rng[:, 0], -np.inf)
    hi = np.where(limited, rng[:, 1], np.inf)
    adr = np.asarray(mj.jnt_qposadr)
    file_low, file_high = np.empty(n), np.empty(n)
    file_low[adr], file_high[adr] = lo, hi
    q_low = file_low if q_low is None else q_low
    q_high = file_high if q_high is None else q_high
    is_hinge = np.empty(n, bool)
    is_hinge[adr] = np.asarray(mj.jnt_type) == hinge
    if sample_low is None:
        ql = vector("q_low", q_low, n)
        sample_low = np.where(np.isfinite(ql), ql, np.where(is_hinge, -np.pi, ql))
    if sample_high is None:
        qh = vector("q_high", q_high, n)
        sample_high = np.where(np.isfinite(qh), qh, np.where(is_hinge, np.pi, qh))

    if fk == "mjx":
        pose_fn = MjxSitePose(int(site_id))
    elif fk == "chain":
        body = int(mj.site_bodyid[site_id])
        path = []
        while body != 0:
            path.append(body)
            body = int(mj.body_parentid[body])
        path = path[::-1]
        joints = []
        for b in path:
            start, num = int(mj.body_jntadr[b]), int(mj.body_jntnum[b])
            joints.append(
                tuple((j, int(mj.jnt_qposadr[j]), int(mj.jnt_type[j]) == hinge) for j in range(start, start + num))
            )
        pose_fn = ChainSitePose(int(site_id), tuple(path), tuple(joints))
    else:
        raise ValueError(f"fk must be 'mjx' or 'chain', got {fk!r}")

    model = mjx.put_model(mj)
    if name is None:
        name = os.path.splitext(os.path.basename(label))[0] if label[0] != "<" else "mjcf"
    return make_system(
        name=name,
        params=model,
        pose_fn=pose_fn,
        has_rotation=True,
        n_act=n,
        task_dim=task_dim,
        q_low=q_low,
        q_high=q_high,
        dq_max=dq_max,
        m_a=m_a,
        sample_low=sample_low,
        sample_high=sample_high,
        min_sigma=min_sigma,
    )
