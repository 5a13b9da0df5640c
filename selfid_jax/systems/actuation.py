"""Actuator coordinates of an MJCF model: the static affine map ``q (n_act,) -> qpos (nq,)`` and limits.

``q_i`` is actuator ``i``'s transmission length without gear (rad / m): its
joint's ``qpos`` (joint transmission on a hinge/slide) or its fixed tendon's
length ``sum_k coef_k qpos_k``. With the active linear joint/tendon equalities
(``y - y0 = a0 + a1 (x - x0)``) and ``joints_fixed`` these are linear
constraints ``C qpos = d(q)``; the map is the least-norm joint motion from
``qpos_ref`` (``qpos0``, ``joints_fixed`` applied) meeting them,
``qpos(q) = qpos_ref + C^+ (d(q) - C qpos_ref) = offset + A q``: a joint
actuator sets its joint exactly, a lone tendon moves joint ``k`` by
``coef_k (q - L_ref) / sum coef^2``, equality followers follow their drivers,
everything else (free and ball joints included) stays at ``qpos_ref``.
Eager numpy, run once per build.
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

__all__ = ["QposMap", "Actuation", "build_actuation", "joint_label", "joint_type_name"]


@dataclasses.dataclass(frozen=True)
class QposMap:
    """Static affine map ``qpos = offset + A q`` from actuator to generalised coordinates.

    Hashable by value (tuples), so pose maps holding it share compiled code.

    Attributes:
      offset: ``(nq,)`` qpos at ``q = 0`` (rad / m; free-joint quaternions included).
      matrix: ``(nq, n_act)`` rows of ``A``.
      names: ``(n_act,)`` actuator names (``actuators="joints"``: joint names).
    """

    offset: tuple[float, ...]
    matrix: tuple[tuple[float, ...], ...]
    names: tuple[str, ...]

    @property
    def A(self) -> np.ndarray:
        """``(nq, n_act)`` float64 map matrix."""
        return np.asarray(self.matrix, dtype=np.float64).reshape(len(self.offset), len(self.names))

    @property
    def b(self) -> np.ndarray:
        """``(nq,)`` float64 offset."""
        return np.asarray(self.offset, dtype=np.float64)

    def __call__(self, q):
        """Full ``qpos (nq,)`` at actuator coordinates ``q (n_act,)``."""
        return self.rows(q, range(len(self.offset)))

    def rows(self, q, addrs):
        """``qpos[addrs]`` at ``q (n_act,)``: a gather where each row has one unit entry, else ``b + A q``."""
        addrs = np.asarray(list(addrs), dtype=np.int64)
        A, b = self.A[addrs], self.b[addrs]
        dtype = jnp.result_type(q, float)
        nz = A != 0
        if np.all(nz.sum(axis=1) <= 1):
            idx = np.where(nz.any(axis=1), nz.argmax(axis=1), 0)
            scale = A[np.arange(len(addrs)), idx]
            x = q[idx]
            if np.all(scale == 1.0) and np.all(b == 0.0):
                return x  # pure selection: q = qpos exactly
            return jnp.asarray(b, dtype) + jnp.asarray(scale, dtype) * x
        return jnp.asarray(b, dtype) + jnp.asarray(A, dtype) @ q

    def pullback(self, cols, zero):
        """``(6, n_act)`` actuator Jacobian ``sum_k J_k A[k, i]`` from ``cols = [(qpos address k, J_k (6,))]``."""
        A = self.A
        out = []
        for i in range(A.shape[1]):
            terms = [c if A[k, i] == 1.0 else A[k, i] * c for k, c in cols if A[k, i] != 0.0]
            out.append(functools.reduce(lambda x, y: x + y, terms) if terms else zero)
        return jnp.stack(out, axis=1)


class Actuation(NamedTuple):
    """Result of :func:`build_actuation` (eager numpy; ``n = n_act``)."""

    qmap: QposMap  # the actuator -> qpos map (and actuator names)
    descs: tuple[str, ...]  # (n,) what each actuator drives, for messages
    home: np.ndarray  # (n,) actuator coordinates at qpos_ref
    low: np.ndarray  # (n,) limits (see build_actuation), may be -inf
    high: np.ndarray  # (n,) may be +inf
    hinge_only: np.ndarray  # (n,) True where the actuator moves hinge joints only (rad units)
    lengths: np.ndarray | None = None  # (n, nq) actuator coordinates of a qpos: q = lengths @ qpos


def joint_type_name(t) -> str:
    """``'free'``, ``'ball'``, ``'slide'`` or ``'hinge'`` for a ``mjtJoint`` value."""
    import mujoco

    return mujoco.mjtJoint(int(t)).name.removeprefix("mjJNT_").lower()


def _label(mj, i, kind="joint") -> str:
    """``'name'`` (quoted) or ``unnamed <kind> #i`` of object ``i`` of type ``kind`` (joint, tendon, equality)."""
    import mujoco

    name = mujoco.mj_id2name(mj, getattr(mujoco.mjtObj, f"mjOBJ_{kind.upper()}"), int(i))
    return repr(name) if name else f"unnamed {kind} #{int(i)}"


joint_label = _label


def _actuator_row(mj, i):
    """``(row (nq,), joints, description)`` of actuator ``i``, or ``(None, None, why unusable)``."""
    import mujoco

    row = np.zeros(mj.nq)
    trn, target = int(mj.actuator_trntype[i]), int(mj.actuator_trnid[i, 0])
    if trn in (mujoco.mjtTrn.mjTRN_JOINT, mujoco.mjtTrn.mjTRN_JOINTINPARENT):
        t = joint_type_name(mj.jnt_type[target])
        if t not in ("hinge", "slide"):
            return None, None, f"drives the {t} joint {joint_label(mj, target)}"
        row[mj.jnt_qposadr[target]] = 1.0
        return row, [target], f"{t} joint {joint_label(mj, target)}"
    if trn == mujoco.mjtTrn.mjTRN_TENDON:
        tl = _label(mj, target, "tendon")
        row = _tendon_row(mj, target)
        if row is None:
            return None, None, f"drives the spatial tendon {tl} (only fixed tendons are supported)"
        if not np.any(row):
            return None, None, f"drives the fixed tendon {tl} whose coefficients are all zero"
        adr, num = int(mj.tendon_adr[target]), int(mj.tendon_num[target])
        joints = [int(j) for j in mj.wrap_objid[adr : adr + num]]
        return row, joints, f"fixed tendon {tl} over joints {', '.join(joint_label(mj, j) for j in joints)}"
    kind = mujoco.mjtTrn(trn).name.removeprefix("mjTRN_").lower()
    return None, None, f"has a {kind} transmission (only joint and fixed-tendon transmissions are supported)"


def _servo_range(mj, i):
    """Position-servo target range of actuator ``i`` in its coordinate (``ctrl``/``act`` -> length / gear), or None.

    Only for fixed-gain, affine-bias actuators with ``biasprm[1] < 0`` (``<position>``,
    ``<intvelocity>``, Menagerie's ``<general>`` servos): target length ``-(gain ctrl + b0) / b1``.
    Motors and velocity servos have no position range.
    """
    import mujoco

    g, (b0, b1), gear = mj.actuator_gainprm[i, 0], mj.actuator_biasprm[i, :2], mj.actuator_gear[i, 0]
    affine = mj.actuator_biastype[i] == mujoco.mjtBias.mjBIAS_AFFINE
    servo = affine and mj.actuator_gaintype[i] == mujoco.mjtGain.mjGAIN_FIXED
    if not (servo and b1 < 0 and g != 0 and gear != 0):
        return None
    dyn = int(mj.actuator_dyntype[i])
    if dyn == mujoco.mjtDyn.mjDYN_INTEGRATOR:
        if not mj.actuator_actlimited[i]:
            return None
        r = np.asarray(mj.actuator_actrange[i], np.float64)
    elif dyn in (mujoco.mjtDyn.mjDYN_NONE, mujoco.mjtDyn.mjDYN_FILTER, mujoco.mjtDyn.mjDYN_FILTEREXACT):
        if not mj.actuator_ctrllimited[i]:
            return None
        r = np.asarray(mj.actuator_ctrlrange[i], np.float64)
    else:
        return None
    length = r * (g / -b1) + b0 / -b1  # exact r when gain = kp and b0 = 0
    return np.sort(length / gear)


def _equality_rows(mj, qpos_ref):
    """Active linear joint/tendon equalities: ``[(row, rhs, label, nonlinear, driver row or None)]``."""
    import mujoco

    out = []
    for e in range(mj.neq):
        if not mj.eq_active0[e]:
            continue
        t, o1, o2 = int(mj.eq_type[e]), int(mj.eq_obj1id[e]), int(mj.eq_obj2id[e])
        poly = np.asarray(mj.eq_data[e, :5], np.float64)
        label = f"equality {_label(mj, e, 'equality')}"
        if t == mujoco.mjtEq.mjEQ_JOINT:
            y = np.zeros(mj.nq)
            y[mj.jnt_qposadr[o1]] = 1.0
            x = None
            if o2 >= 0:
                x = np.zeros(mj.nq)
                x[mj.jnt_qposadr[o2]] = 1.0
        elif t == mujoco.mjtEq.mjEQ_TENDON:
            y = _tendon_row(mj, o1)
            x = _tendon_row(mj, o2) if o2 >= 0 else None
            if y is None or (o2 >= 0 and x is None):
                continue  # couples spatial tendons: not a joint-space constraint, ignored
        else:
            continue  # connect / weld / distance / flex: not joint couplings, ignored for kinematics
        row = y - (poly[1] * x if x is not None else 0.0)
        rhs = y @ qpos_ref + poly[0] - (poly[1] * (x @ qpos_ref) if x is not None else 0.0)
        out.append((row, rhs, label, bool(np.any(poly[2:] != 0)), x))
    return out


def _tendon_row(mj, t):
    """Coefficient row ``(nq,)`` of fixed tendon ``t`` (length ``row @ qpos``), None for a spatial tendon."""
    import mujoco

    adr, num = int(mj.tendon_adr[t]), int(mj.tendon_num[t])
    if num == 0 or np.any(mj.wrap_type[adr : adr + num] != mujoco.mjtWrap.mjWRAP_JOINT):
        return None
    row = np.zeros(mj.nq)
    for j, c in zip(mj.wrap_objid[adr : adr + num], mj.wrap_prm[adr : adr + num]):
        row[mj.jnt_qposadr[int(j)]] += c
    return row


# One chosen actuator: (name, row (nq,), joints, description, MuJoCo actuator id or None for a bare joint).
_Chosen = tuple[str, np.ndarray, list[int], str, int | None]


def _select(mj, actuators, label) -> list[_Chosen]:
    """``[(name, row, joints, desc, actuator id or None)]`` of the chosen actuators."""
    import mujoco

    scalar = [j for j in range(mj.njnt) if joint_type_name(mj.jnt_type[j]) in ("hinge", "slide")]
    if isinstance(actuators, str) and actuators == "joints":
        if not scalar:
            raise ValueError(f"MJCF {label} has no hinge or slide joints: nothing to actuate")
        out: list[_Chosen] = []
        for j in scalar:
            row = np.zeros(mj.nq)
            row[mj.jnt_qposadr[j]] = 1.0
            name = mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint{j}"
            out.append((name, row, [j], f"{joint_type_name(mj.jnt_type[j])} joint {joint_label(mj, j)}", None))
        return out
    names = [mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_ACTUATOR, i) or f"actuator{i}" for i in range(mj.nu)]
    if actuators is None:
        if mj.nu == 0 and not scalar:
            raise ValueError(f"MJCF {label} has no actuators and no hinge or slide joints: nothing to actuate")
        if mj.nu == 0:
            raise ValueError(
                f"MJCF {label} has no actuators (it has {len(scalar)} hinge/slide joint(s)); add <actuator> "
                "elements, or pass actuators='joints' to drive every hinge and slide joint directly"
            )
        ids = list(range(mj.nu))
    else:
        if isinstance(actuators, str):
            raise ValueError(f"actuators must be None, 'joints' or a list of actuator names, got {actuators!r}")
        ids = []
        for a in actuators:
            if a not in names:
                raise ValueError(f"unknown actuator {a!r} in MJCF {label}; its actuators are {names}")
            if names.index(a) in ids:
                raise ValueError(f"actuator {a!r} is listed twice in actuators")
            ids.append(names.index(a))
        if not ids:
            raise ValueError("actuators is empty: name at least one actuator")
    out, skipped = [], list[str]()
    for i in ids:
        row, joints, desc = _actuator_row(mj, i)
        if row is None:
            if actuators is not None:
                raise ValueError(f"actuator {names[i]!r} {desc}")
            skipped.append(f"{names[i]!r} {desc}")
            continue
        out.append((names[i], row, joints, desc, i))
    if not out:
        raise ValueError(f"MJCF {label} has no usable actuators: " + "; ".join(skipped))
    if skipped:
        warnings.warn(f"from_mjcf: skipped actuators of MJCF {label}: " + "; ".join(skipped), stacklevel=4)
    return out


def _solve(C, rhs0, ref, n_act):
    """``(A (nq, n_act), offset (nq,))`` of ``qpos = ref + C^+ (d - C ref)`` per connected block of ``C``.

    The last ``n_act`` rows of ``C`` are the actuator rows (``d = q``), the others have ``d = rhs0``.
    Blocks of one unit row (a joint actuator) are solved exactly: ``A`` entry 1, offset 0.
    """
    nq = C.shape[1]
    A, offset = np.zeros((nq, n_act)), ref.copy()
    parent = list(range(nq))

    def find(k):
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    for row in C:
        cols = np.flatnonzero(row)
        for c in cols[1:]:
            parent[find(c)] = find(cols[0])
    blocks: dict[int, list[int]] = {}
    for r, row in enumerate(C):
        blocks.setdefault(find(int(np.flatnonzero(row)[0])), []).append(r)
    first_act = C.shape[0] - n_act
    for rows in blocks.values():
        cols = np.flatnonzero(np.any(C[rows] != 0, axis=0))
        Cb = C[np.ix_(np.asarray(rows), cols)]
        d0 = np.array([rhs0[r] if r < first_act else 0.0 for r in rows])
        pinv = (1.0 / Cb) if Cb.shape == (1, 1) else np.linalg.pinv(Cb)
        offset[cols] = ref[cols] + pinv @ (d0 - Cb @ ref[cols])
        for k, r in enumerate(rows):
            if r >= first_act:
                A[cols, r - first_act] = pinv[:, k]
    A[np.abs(A) < 1e-14 * max(1.0, np.abs(A).max(initial=0.0))] = 0.0
    return A, offset


def build_actuation(mj, *, actuators=None, joints_fixed=None, label="MJCF") -> Actuation:
    """Actuator coordinates, the ``q -> qpos`` map, home and limits of ``mj`` (see the module docstring).

    Args:
      mj: ``mujoco.MjModel``.
      actuators: None (every actuator with a joint or fixed-tendon transmission;
        others are skipped with a warning), a list of actuator names, or
        ``"joints"`` (every hinge/slide joint is an actuator, ``q_i = qpos_j``).
      joints_fixed: ``{joint name: value}`` (rad / m) for hinge/slide joints no
        chosen actuator drives (default: ``qpos0``).
      label: model label for messages.

    Limits (``low``, ``high``, actuator units): the intersection of (a) the
    ranges of limited joints the actuator moves (other actuators at home),
    (b) the tendon's ``range`` if limited, (c) for position servos the target
    range of ``ctrlrange`` (``actrange`` for integrator dynamics) mapped to a
    length (see :func:`_servo_range`); +-inf where none applies.

    Raises:
      ValueError: unknown names, no usable actuators, actuators/constraints
        that are not independent, nonlinear equalities on driven joints, empty limits.
    """
    import mujoco

    qpos_ref = np.asarray(mj.qpos0, np.float64).copy()
    fixed_rows = []
    for name, value in dict(joints_fixed or {}).items():
        j = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_JOINT, str(name))
        t = joint_type_name(mj.jnt_type[j]) if j >= 0 else None
        if t not in ("hinge", "slide"):
            known = [mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_JOINT, k) for k in range(mj.njnt)]
            why = f"is a {t} joint" if t else f"is not a joint of MJCF {label} (joints: {known})"
            raise ValueError(f"joints_fixed: {name!r} {why}; only hinge and slide joints can be fixed to a value")
        row = np.zeros(mj.nq)
        row[mj.jnt_qposadr[j]] = 1.0
        qpos_ref[mj.jnt_qposadr[j]] = float(value)
        fixed_rows.append((row, float(value), f"joints_fixed[{name!r}]"))
    chosen = _select(mj, actuators, label)
    eqs = _equality_rows(mj, qpos_ref)

    # Rows in order equalities, fixed joints, actuators; each must be independent of the earlier ones.
    basis = np.zeros((0, mj.nq))
    rows: list[np.ndarray] = []
    rhs: list[float] = []
    labels: list[str] = []
    for kind, items in (("eq", [(r, b, lb) for r, b, lb, _, _ in eqs]), ("fix", fixed_rows),
                        ("act", [(r, 0.0, f"actuator {n!r} ({d})") for n, r, _, d, _ in chosen])):
        for row, b, lb in items:
            res = row - basis.T @ (basis @ row)
            res = res - basis.T @ (basis @ res)
            if np.linalg.norm(res) <= 1e-9 * np.linalg.norm(row):
                if kind == "eq":
                    continue  # a redundant coupling: drop it
                near = [labels[k] for k, r in enumerate(rows) if np.any((r != 0) & (row != 0))]
                raise ValueError(
                    f"{lb} is not independent of {', '.join(near) or 'the other constraints'}: the joints it "
                    "moves are already determined; choose a subset with actuators=[...] or drop the joints_fixed entry"
                )
            basis = np.vstack([basis, res / np.linalg.norm(res)])
            rows.append(row)
            rhs.append(b)
            labels.append(lb)
    n = len(chosen)
    C = np.stack(rows)
    A, offset = _solve(C, np.asarray(rhs), qpos_ref, n)
    for _row, _, lb, nonlinear, x in eqs:
        if nonlinear and x is not None and np.any(x @ A != 0):
            raise ValueError(f"{lb} is a nonlinear polynomial coupling of driven joints; only a0 + a1 x is supported")

    C_act = np.stack([c[1] for c in chosen])
    home = C_act @ qpos_ref
    base = offset + A @ home
    low, high, descs = np.full(n, -np.inf), np.full(n, np.inf), []
    for i, (name, _, _, desc, aid) in enumerate(chosen):
        bounds = []
        for j in range(mj.njnt):
            a = A[mj.jnt_qposadr[j], i] if joint_type_name(mj.jnt_type[j]) in ("hinge", "slide") else 0.0
            if a != 0.0 and mj.jnt_limited[j]:
                rest = base[mj.jnt_qposadr[j]] - a * home[i]
                bounds.append(np.sort((np.asarray(mj.jnt_range[j], np.float64) - rest) / a))
        if aid is not None:
            if mj.actuator_trntype[aid] == mujoco.mjtTrn.mjTRN_TENDON and mj.tendon_limited[mj.actuator_trnid[aid, 0]]:
                bounds.append(np.asarray(mj.tendon_range[mj.actuator_trnid[aid, 0]], np.float64))
            servo = _servo_range(mj, aid)
            if servo is not None:
                bounds.append(servo)
        for lo, hi in bounds:
            low[i], high[i] = max(low[i], lo), min(high[i], hi)
        if not low[i] < high[i]:
            raise ValueError(f"actuator {name!r} ({desc}): its joint, tendon and servo ranges do not overlap")
        descs.append(desc)
    scalar_addr = {int(mj.jnt_qposadr[j]): joint_type_name(mj.jnt_type[j]) for j in range(mj.njnt)
                   if joint_type_name(mj.jnt_type[j]) in ("hinge", "slide")}
    hinge_only = np.array([all(scalar_addr.get(int(k)) == "hinge" for k in np.flatnonzero(A[:, i])) for i in range(n)])
    qmap = QposMap(
        offset=tuple(float(v) for v in offset),
        matrix=tuple(tuple(float(v) for v in r) for r in A),
        names=tuple(c[0] for c in chosen),
    )
    return Actuation(qmap=qmap, descs=tuple(descs), home=home, low=low, high=high, hinge_only=hinge_only,
                     lengths=C_act)
