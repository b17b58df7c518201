"""How far posed cameras are from known ones (structure from motion against ground truth)."""

from __future__ import annotations

import numpy as np


def pose_errors(c2w: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """How far posed cameras are from known ones, after the similarity that best aligns their centres.

    The similarity (s, R, t) minimises sum_i |r_i - (s R c_i + t)|^2 over the camera centres c_i
    (``c2w``) and r_i (``reference``), in closed form (Umeyama 1991): with the centred centres'
    covariance Sigma = U D V^T, R = U S V^T, S = diag(1, 1, det(U V^T)), s = tr(D S) / var(c).

    Args:
        c2w: [N, 3, 4] or [N, 4, 4] float64 camera-to-world of the posed cameras (OpenGL).
        reference: the same cameras' known poses, same shape and convention, any frame and scale.

    Returns:
        rotation error [N] float64 in degrees (angle of R_ref^T R R_est), centre error [N]
        float64 in the reference's units, and the reference cameras' mean distance from their centroid.
    """
    est, ref = np.asarray(c2w, dtype=np.float64)[:, :3], np.asarray(reference, dtype=np.float64)[:, :3]
    c, r = est[:, :, 3], ref[:, :, 3]
    c0, r0 = c - c.mean(0), r - r.mean(0)
    u, d, vt = np.linalg.svd(r0.T @ c0 / len(c))
    sign = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ sign @ vt
    scale = float(np.trace(np.diag(d) @ sign) / (c0 ** 2).sum(1).mean())
    centre_error = np.linalg.norm(scale * c0 @ rotation.T - r0, axis=1)
    relative = np.swapaxes(ref[:, :, :3], 1, 2) @ rotation @ est[:, :, :3]
    cos = np.clip((np.trace(relative, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return np.degrees(np.arccos(cos)), centre_error, float(np.linalg.norm(r0, axis=1).mean())
