"""Serial arms from an Elementary Transform Sequence (ETS): :func:`from_ets` and the seed's 5-DOF arm :func:`arm5`.

An ETS writes the end-effector pose as a product of elementary transforms
(Haviland and Corke, "Manipulator Differential Kinematics", arXiv 2207.01796;
seed 004 uses it for its 5-DOF arm)::

    T(q) = E_1 E_2 ... E_k,   E_j in {tx(c), ty(c), tz(c), Rx(c), Ry(c), Rz(c)}  (constants)
                                      or {tx, ty, tz, Rx, Ry, Rz}(q_i)             (joints)

Constants are metres (``t*``) and radians (``R*``); each joint variable is one
actuator, in order of appearance. Consecutive constants fold into one rigid
transform, so the walk is ``C_0 J_1(q_1) C_1 ... J_n(q_n) C_n`` and costs one
matrix product per joint. The pose and the world-frame geometric Jacobian come
from the same walk (:class:`EtsPose`): column ``i`` is ``s_i [a_i x (p - o_i);
a_i]`` for a revolute joint and ``s_i [a_i; 0]`` for a prismatic one (``a_i``
the joint axis in the world, ``o_i`` a point on it, ``s_i = -1`` for a flipped
joint), the convention of ``roboticstoolbox`` ``ETS.jacob0`` and MuJoCo's
``mj_jacSite``.

``roboticstoolbox-python`` is optional: :func:`from_ets` also takes its ``ETS``
objects (duck-typed, never imported here), including flipped joints, joint
offsets, ``jindex`` orderings and per-joint ``qlim``.
"""

from __future__ import annotations

import ast
import dataclasses
import math
import operator
import re
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from selfid_jax.systems.system import System, make_system
from selfid_jax.systems.validation import Limits, Values

__all__ = ["ARM5_ETS", "ARM5_HOME", "ARM5_Q_HIGH", "ARM5_Q_LOW", "EtsModel", "EtsPose", "arm5", "from_ets", "parse_ets"]

_AXES = {"x": 0, "y": 1, "z": 2}


# ------------------------------------------------------------------ parsing
@dataclasses.dataclass(frozen=True)
class _Element:
    """One elementary transform: ``kind`` in ``"R"``/``"t"``, ``axis`` 0..2, a constant ``value`` or a joint."""

    kind: str
    axis: int
    value: float | None  # constant (m or rad); None for a joint
    sign: float = 1.0  # -1 for a flipped joint (moves by -q)
    offset: float = 0.0  # joint moves by sign * q + offset
    jindex: int | None = None
    qlim: tuple[float, float] | None = None


_TOKEN = re.compile(r"^\s*([RrTt])\s*([xyzXYZ])\s*(?:\(\s*(.*?)\s*\))?\s*$")
_JOINT_ARG = re.compile(r"^(-)?\s*q\s*(\d+)?$")
_BINOPS = {ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul, ast.Div: operator.truediv,
           ast.Pow: operator.pow}


def _number(text: str, where: str) -> float:
    """A finite float from ``text``: a literal or arithmetic on literals and ``pi`` (``"pi/2"``, ``"-0.5*pi"``)."""

    def ev(node):
        if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) and not isinstance(node.value, bool):
            return float(node.value)
        if isinstance(node, ast.Name) and node.id == "pi":
            return math.pi
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
            v = ev(node.operand)
            return -v if isinstance(node.op, ast.USub) else v
        if isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
            return _BINOPS[type(node.op)](ev(node.left), ev(node.right))
        raise ValueError

    try:
        value = ev(ast.parse(text, mode="eval").body)
    except (SyntaxError, ValueError, ZeroDivisionError, OverflowError):
        raise ValueError(f"{where}: cannot read {text!r} as a number (a literal, or arithmetic with pi)") from None
    if not math.isfinite(value):
        raise ValueError(f"{where}: the constant must be finite, got {text!r}")
    return value


def _parse_string(text: str, j: int) -> _Element:
    where = f"ETS element {j} ({text!r})"
    m = _TOKEN.match(text)
    if m is None:
        raise ValueError(f"{where}: expected tx/ty/tz/Rx/Ry/Rz, optionally with a constant in parentheses, "
                         "e.g. 'tz(0.1)', 'Rz(pi/2)', or a joint variable 'Rz' / 'Rz(q3)' / 'Rz(-q)'")
    kind, axis, arg = m.group(1), _AXES[m.group(2).lower()], m.group(3)
    kind = "R" if kind in "Rr" else "t"
    if arg is None or arg == "":
        if arg == "":
            raise ValueError(f"{where}: empty parentheses; write the joint as '{kind}{'xyz'[axis]}' or give a constant")
        return _Element(kind, axis, None)
    jm = _JOINT_ARG.match(arg)
    if jm is not None:
        return _Element(kind, axis, None, sign=-1.0 if jm.group(1) else 1.0,
                        jindex=None if jm.group(2) is None else int(jm.group(2)))
    return _Element(kind, axis, _number(arg, where))


def _is_rtb_ets(ets) -> bool:
    return hasattr(ets, "__iter__") and all(hasattr(ets, a) for a in ("n", "fkine", "jacob0"))


def _from_rtb_joint(e, j: int) -> _Element:
    """The joint of one roboticstoolbox ``ET`` (flip, offset, ``jindex`` and ``qlim`` kept)."""
    axis_name = str(e.kind if hasattr(e, "kind") else e.axis)  # .axis is deprecated in roboticstoolbox 1.4
    if axis_name not in ("Rx", "Ry", "Rz", "tx", "ty", "tz"):
        raise ValueError(f"ETS element {j} ({e}): unsupported joint type {axis_name!r}")
    qlim = None if e.qlim is None else (float(e.qlim[0]), float(e.qlim[1]))
    return _Element(axis_name[0], _AXES[axis_name[1]], None, sign=-1.0 if e.isflip else 1.0,
                    offset=float(getattr(e, "_offset", 0.0) or 0.0), jindex=e.jindex, qlim=qlim)


def _element_T(el: _Element, value: float) -> np.ndarray:
    T = np.eye(4)
    if el.kind == "t":
        T[el.axis, 3] = value
    else:
        c, s = math.cos(value), math.sin(value)
        i, k = [(1, 2), (2, 0), (0, 1)][el.axis]
        T[i, i], T[i, k], T[k, i], T[k, k] = c, -s, s, c
    return T


def parse_ets(ets) -> list[Any]:
    """Normalise an ETS to a list of elements: constant 4x4 ``numpy`` transforms and joint :class:`_Element` s.

    Accepts a list (or tuple) of strings, one string with elements separated by
    whitespace or ``⊕`` (the form ``roboticstoolbox`` prints), or a
    ``roboticstoolbox`` ``ETS``. Raises ``ValueError`` naming the bad element.
    """
    if isinstance(ets, str):
        items = [s for s in re.split(r"[\s⊕]+", ets.strip()) if s]
    elif _is_rtb_ets(ets):
        out: list[Any] = []
        for j, e in enumerate(ets):
            if e.isjoint:
                out.append(_from_rtb_joint(e, j))
                continue
            T = np.asarray(e.A(), dtype=np.float64)
            if T.shape != (4, 4):
                raise ValueError(f"ETS element {j} ({e}): only 3-D transforms are supported, got {T.shape}")
            out.append(T)
        return out
    elif isinstance(ets, (list, tuple)):
        items = list(ets)
    else:
        raise ValueError(f"ets must be a list of strings such as ['tz(0.1)', 'Rz'], one such string, or a "
                         f"roboticstoolbox ETS; got {type(ets).__name__}")
    out = []
    for j, s in enumerate(items):
        if not isinstance(s, str):
            raise ValueError(f"ETS element {j}: expected a string such as 'tz(0.1)' or 'Rz', got {s!r}")
        el = _parse_string(s, j)
        out.append(el if el.value is None else _element_T(el, el.value))
    return out


# ------------------------------------------------------------------ the pose map
@dataclasses.dataclass(frozen=True)
class EtsModel:
    """The constant transforms of an ETS between its joints, a traced pytree (a sweep may vmap over them).

    ``T(q) = C_0 J_1(q_1) C_1 ... J_n(q_n) C_n`` with ``C_i = (rot[i], pos[i])``.
    """

    rot: jax.Array  # (n + 1, 3, 3) rotations of the folded constants C_0..C_n
    pos: jax.Array  # (n + 1, 3) translations of C_0..C_n [m]

    def replace(self, **changes) -> EtsModel:
        """``dataclasses.replace`` (e.g. other link lengths)."""
        return dataclasses.replace(self, **changes)


jax.tree_util.register_dataclass(EtsModel, data_fields=["rot", "pos"], meta_fields=[])


def _axis_rotation(axis: int, angle):
    """``(3, 3)`` rotation by ``angle`` (rad) about coordinate axis ``axis`` (0, 1, 2), elementwise cos/sin."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    one, zero = jnp.ones_like(c), jnp.zeros_like(c)
    if axis == 0:
        rows = [[one, zero, zero], [zero, c, -s], [zero, s, c]]
    elif axis == 1:
        rows = [[c, zero, s], [zero, one, zero], [-s, zero, c]]
    else:
        rows = [[c, -s, zero], [s, c, zero], [zero, zero, one]]
    return jnp.stack([jnp.stack(r) for r in rows])


@dataclasses.dataclass(frozen=True)
class EtsPose:
    """Pose map of an ETS chain: ``(EtsModel, q (n,)) -> (p (3,), R (3, 3))``; Jacobian from the same walk.

    Static, hashable by value (rebuilding the same arm does not recompile).

    Attributes:
      axes: per joint, the coordinate axis 0/1/2 (x/y/z) in the joint's frame.
      revolute: per joint, True for ``R*`` (rad), False for ``t*`` (m).
      signs: per joint, +1 or -1 (a flipped joint moves by ``-q``).
      qidx: per joint (in chain order), its index in ``q``.
    """

    axes: tuple[int, ...]
    revolute: tuple[bool, ...]
    signs: tuple[float, ...]
    qidx: tuple[int, ...]

    def __call__(self, model: EtsModel, q):
        p, R, _ = self._walk(model, q)
        return p, R

    def jacobian(self, model: EtsModel, q):
        """World-frame geometric Jacobian ``(6, n)``, rows ``[dp/dq (m per rad or m); omega/dq]``."""
        return self.pose_and_jacobian(model, q)[1]

    def pose_and_jacobian(self, model: EtsModel, q):
        """``((p (3,), R (3, 3)), J (6, n))`` from one walk of the chain."""
        p, R, joints = self._walk(model, q)
        cols: dict[int, jax.Array] = {}  # by actuator index (qidx is a permutation)
        for i, (a, o) in enumerate(joints):
            s = self.signs[i]
            if self.revolute[i]:
                col = jnp.concatenate([jnp.cross(a, p - o), a])
            else:
                col = jnp.concatenate([a, jnp.zeros(3, p.dtype)])
            cols[self.qidx[i]] = s * col
        return (p, R), jnp.stack([cols[k] for k in range(len(self.axes))], axis=1)

    def _walk(self, model: EtsModel, q):
        """End pose and, per joint in chain order, ``(world axis (3,), point on the axis (3,))``."""
        q = jnp.asarray(q)
        dtype = jnp.result_type(q, model.pos)
        rots, poss = model.rot.astype(dtype), model.pos.astype(dtype)
        q = q.astype(dtype)
        rot, pos = rots[0], poss[0]
        joints = []
        for i, (axis, rev) in enumerate(zip(self.axes, self.revolute)):
            a = rot[:, axis]
            joints.append((a, pos))
            v = self.signs[i] * q[self.qidx[i]]
            if rev:
                rot = rot @ _axis_rotation(axis, v)
            else:
                pos = pos + a * v
            pos = pos + rot @ poss[i + 1]
            rot = rot @ rots[i + 1]
        return pos, rot, joints


def _compile(elements: list) -> tuple[EtsPose, np.ndarray, np.ndarray, list]:
    """Fold constants around the joints: ``(EtsPose, rot (n+1, 3, 3), pos (n+1, 3), joint elements)``."""
    consts = [np.eye(4)]
    joints: list[_Element] = []
    for el in elements:
        if isinstance(el, np.ndarray):
            consts[-1] = consts[-1] @ el
            continue
        if el.offset != 0.0:  # E(s q + a) = E(a) E(s q) for one axis: the offset joins the constant before
            consts[-1] = consts[-1] @ _element_T(el, el.offset)
        joints.append(el)
        consts.append(np.eye(4))
    n = len(joints)
    if n == 0:
        raise ValueError("the ETS has no joint variable: give at least one of Rx, Ry, Rz, tx, ty, tz "
                         "without a constant")
    given = [el.jindex for el in joints]
    present = [g for g in given if g is not None]
    if not present:
        qidx = tuple(range(n))
    elif len(present) == n and sorted(present) == list(range(n)):
        qidx = tuple(int(g) for g in present)
    else:
        raise ValueError(f"joint indices must be all absent or a permutation of 0..{n - 1}, got {given}")
    pose = EtsPose(axes=tuple(el.axis for el in joints), revolute=tuple(el.kind == "R" for el in joints),
                   signs=tuple(float(el.sign) for el in joints), qidx=qidx)
    T = np.stack(consts)
    ordered: list[_Element | None] = [None] * n
    for el, k in zip(joints, qidx):
        ordered[k] = el
    return pose, T[:, :3, :3], T[:, :3, 3], ordered


def from_ets(
    ets,
    *,
    task_dim: int = 3,
    q_low: Values | None = None,
    q_high: Values | None = None,
    m_a: Values = 0.03,
    dq_max: Values = 0.1,
    sample_low: Values | None = None,
    sample_high: Values | None = None,
    min_sigma: float = 1e-3,
    name: str = "ets",
) -> System:
    """A serial arm from an Elementary Transform Sequence: actuator ``q (n,)`` -> end-effector pose.

    The ETS is a list of strings (``["tz(0.1)", "Rz", "Ry", "tz(0.15)", ...]``;
    constants ``tx(c)``, ``ty(c)``, ``tz(c)`` in m and ``Rx(c)``, ``Ry(c)``,
    ``Rz(c)`` in rad, ``c`` a literal or arithmetic with ``pi``; joint variables
    ``Rx``, ``Ry``, ``Rz`` (rad), ``tx``, ``ty``, ``tz`` (m), also written
    ``Rz(q3)`` or ``Rz(-q)`` for a flipped joint), the same as one string, or a
    ``roboticstoolbox`` ``ETS`` object. One actuator per joint variable, in
    order (or by ``jindex``). World frame = the ETS's base frame. The pose map
    :class:`EtsPose` gives the pose and the geometric Jacobian from one pass
    (``System.pose_and_jacobian``).

    Args:
      ets: the sequence (see above).
      task_dim: 3 (position, default), 6 (position + rotation vector) or 2 (xy).
      q_low, q_high: joint limits, scalar or ``(n,)`` (rad / m). Default: each
        joint's ``qlim`` for a roboticstoolbox ETS, else ``-pi``/``pi`` for
        revolute joints; prismatic joints without ``qlim`` need them given.
      m_a: safe self-ID magnitude, scalar or ``(n,)`` (rad / m).
      dq_max: largest actuator step per control step, scalar or ``(n,)``.
      sample_low, sample_high: box of start configurations (default: the limits).
      min_sigma: ``sample_configs`` keeps configurations whose task Jacobian's
        smallest singular value exceeds this.
      name: label.

    Returns:
      A :class:`~selfid_jax.systems.System` whose ``params`` is an
      :class:`EtsModel` and ``pose_fn`` an :class:`EtsPose`.

    Raises:
      ValueError: a bad element (named by index), no joint, or bad limits
        (e.g. ``q_low >= q_high``), before any compute.
    """
    pose, rot, pos, joints = _compile(parse_ets(ets))
    n = len(joints)
    if q_low is None or q_high is None:
        default = []
        for k, el in enumerate(joints):
            if el.qlim is not None:
                default.append(el.qlim)
            elif el.kind == "R":
                default.append((-math.pi, math.pi))
            else:
                raise ValueError(f"joint {k} ({'t' + 'xyz'[el.axis]}) is prismatic: give q_low and q_high (m)")
        lo, hi = np.asarray(default, dtype=np.float64).T
        q_low = lo if q_low is None else q_low
        q_high = hi if q_high is None else q_high
    fl = jnp.result_type(float)
    model = EtsModel(rot=jnp.asarray(rot, fl), pos=jnp.asarray(pos, fl))
    return make_system(name=name, params=model, pose_fn=pose, has_rotation=True,
                       limits=Limits(n, task_dim, q_low, q_high, dq_max, m_a, sample_low, sample_high, min_sigma))


# ------------------------------------------------------------------ the seed's 5-DOF arm
ARM5_ETS = ("tz(0.10)", "Rz", "Ry", "tz(0.15)", "Ry", "tz(0.15)", "Ry", "tz(0.06)", "Rz", "tz(0.04)")
"""Seed 004's desktop arm: base yaw, shoulder, elbow and wrist pitch (``Ry``), wrist roll; links
0.10/0.15/0.15/0.10 m."""

ARM5_Q_LOW = (-2.6, -1.6, -2.4, -1.9, -2.6)
ARM5_Q_HIGH = (2.6, 1.6, 2.4, 1.9, 2.6)
"""Joint limits (rad): base and roll +-149 deg, shoulder +-92 deg from vertical, elbow +-138 deg, wrist pitch +-109 deg.

Our choice (the slides give none), in the range of the hobby-servo desktop arms the seed shows: a servo turns about
300 deg, the shoulder stops near horizontal, the elbow and wrist stop before the links fold onto each other."""

ARM5_HOME = (0.0, 0.4, 0.9, 0.6, 0.0)
"""A working configuration (rad): elbow and wrist bent, tool 19 deg below horizontal, at about (0.30, 0, 0.25) m."""

# Start configurations for self-ID and path following: elbow bent away from straight (|q3| >= 0.3 in the
# box below keeps the position Jacobian well conditioned), shoulder leaning forward, base within +-1.5 rad.
_ARM5_SAMPLE_LOW = (-1.5, -0.4, 0.3, -0.6, -1.5)
_ARM5_SAMPLE_HIGH = (1.5, 1.0, 1.8, 1.5, 1.5)


def arm5(
    *,
    task_dim: int = 3,
    m_a=0.03,
    dq_max: float = 0.1,
    q_low=ARM5_Q_LOW,
    q_high=ARM5_Q_HIGH,
    sample_low=_ARM5_SAMPLE_LOW,
    sample_high=_ARM5_SAMPLE_HIGH,
    min_sigma: float = 0.02,
) -> System:
    """Seed 004's under-actuated 5-DOF desktop arm (:data:`ARM5_ETS`), 5 revolute actuators.

    ``Tz(.10) Rz Ry Tz(.15) Ry Tz(.15) Ry Tz(.06) Rz Tz(.04)``: base yaw, three
    pitch joints about the (rotated) y axis, wrist roll about the tool axis;
    reach 0.40 m from the shoulder at 0.10 m height. The tool has no yaw of its
    own (the slides' "what are we missing"): the 6x5 Jacobian has rank 5 at
    most, and the wrist roll never moves the POM (its column of the position
    Jacobian is zero), so the position task is redundant with 4 effective
    joints.

    Args:
      task_dim: 3 (tool-tip position, default), 6 or 2.
      m_a: safe self-ID magnitude (rad).
      dq_max: per-step actuator limit (rad).
      q_low, q_high: joint limits (rad), default :data:`ARM5_Q_LOW` / :data:`ARM5_Q_HIGH`.
      sample_low, sample_high: box of start configurations (rad), default
        elbow bent ``q3 in [0.3, 1.8]``, shoulder ``[-0.4, 1.0]``.
      min_sigma: ``sample_configs`` threshold on the task Jacobian's smallest
        singular value (m/rad for position).

    Returns:
      A :class:`~selfid_jax.systems.System` named ``"arm5"``.
    """
    return from_ets(list(ARM5_ETS), task_dim=task_dim, q_low=q_low, q_high=q_high, m_a=m_a, dq_max=dq_max,
                    sample_low=sample_low, sample_high=sample_high, min_sigma=min_sigma, name="arm5")
