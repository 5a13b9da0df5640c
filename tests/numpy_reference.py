"""Plain numpy references, written independently of the JAX code: UR5e DH kinematics
and the path-following controller as a Python loop (tests and benchmarks/rollouts.py)."""

from __future__ import annotations

import numpy as np

UR5E_DH_D = np.array([0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996])
UR5E_DH_A = np.array([0.0, -0.425, -0.3922, 0.0, 0.0, 0.0])
UR5E_DH_ALPHA = np.array([np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0])


def ur5e_frames(q):
    """Base-to-joint-frame transforms ``T_0..T_6`` (7, 4, 4) of the standard UR5e DH chain."""
    T = np.eye(4)
    frames = [T]
    for i in range(6):
        ct, st = np.cos(q[i]), np.sin(q[i])
        ca, sa = np.cos(UR5E_DH_ALPHA[i]), np.sin(UR5E_DH_ALPHA[i])
        A = np.array(
            [
                [ct, -st * ca, st * sa, UR5E_DH_A[i] * ct],
                [st, ct * ca, -ct * sa, UR5E_DH_A[i] * st],
                [0.0, sa, ca, UR5E_DH_D[i]],
                [0.0, 0.0, 0.0, 1.0],
            ]
        )
        T = T @ A
        frames.append(T)
    return np.stack(frames)


def ur5e_position(q):
    return ur5e_frames(q)[-1][:3, 3]


def ur5e_position_jacobian(q):
    """Geometric position Jacobian ``(3, 6)``: column i is ``z_{i-1} x (p_e - p_{i-1})``."""
    F = ur5e_frames(q)
    pe = F[-1][:3, 3]
    return np.stack([np.cross(F[i][:3, 2], pe - F[i][:3, 3]) for i in range(6)], axis=1)


def right_inverse(J):
    return J.T @ np.linalg.solve(J @ J.T, np.eye(J.shape[0]))


def follow(position, jinv, path, q0, *, steps, max_step, tol, dq_max, q_low, q_high, gain=1.0, diverge_dist=None):
    """Position-task controller loop; returns (completion, mean_error, max_error, steps_used, failed, positions)."""
    q = np.array(q0, float)
    p0 = position(q)
    d = path.shape[1]
    targets = p0[:d] + path
    verts = np.vstack([p0[:d], targets])
    W = len(targets)
    if diverge_dist is None:
        diverge_dist = 2 * np.max(np.linalg.norm(path, axis=1)) + 10 * tol
    w, failed, err_sum, err_max, used = 0, False, 0.0, 0.0, 0
    positions = []

    def dist_to_path(p):
        best = np.inf
        for a, b in zip(verts[:-1], verts[1:]):
            ab = b - a
            t = np.clip(np.dot(p - a, ab) / max(np.dot(ab, ab), 1e-300), 0, 1)
            best = min(best, np.linalg.norm(p - (a + t * ab)))
        return best

    for _ in range(steps):
        p = position(q)[:d]
        positions.append(p)
        if w >= W or failed:
            continue
        dist = dist_to_path(p)
        if np.linalg.norm(targets[w] - p) <= tol:
            w += 1
            if w >= W:
                continue
        e = gain * (targets[w] - p)
        n = np.linalg.norm(e)
        if n > max_step:
            e = e * max_step / n
        J = jinv(q)
        q_new = np.clip(q + np.clip(J @ e, -dq_max, dq_max), q_low, q_high)
        if not np.all(np.isfinite(q_new)) or dist > diverge_dist:
            failed = True
        else:
            q = q_new
        err_sum += dist
        err_max = max(err_max, dist)
        used += 1
    p = position(q)[:d]
    if w < W and not failed and np.linalg.norm(targets[w] - p) <= tol:
        w += 1
    return w / W, err_sum / max(used, 1), err_max, used, failed, np.array(positions)
