"""EWA projection of 3D Gaussians into pinhole cameras, shared by the CPU backends.

Camera frame: z forward, x right, y down (docs/conventions.md#frames). Pixel (i, j) covers [i, i+1)
x [j, j+1); Gaussians are evaluated at pixel centres (i + 0.5, j + 0.5) — gsplat's convention, so a
point projected to ``u = fx * x / z + cx`` lies inside pixel ``floor(u)``.

The 2D covariance is the standard EWA one, ``Σ' = J W Σ Wᵀ Jᵀ + eps2d·I``, where ``W`` is the
world→camera rotation and ``J`` the projection Jacobian evaluated with ``x/z`` and ``y/z`` clamped
to 1.3x the field of view (off-screen Gaussians then keep a bounded footprint). Numerics
(docs/conventions.md#numerics): quaternions are normalised with an epsilon (a zero quaternion is the
identity rotation, with a finite gradient), depths are clamped to the near plane before any division
(culled Gaussians stay finite), and the 2D determinant is computed by Cauchy–Binet as a sum of
squares, so it can never be negative.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

__all__ = [
    "ALPHA_MIN",
    "ALPHA_MAX",
    "TRANSMITTANCE_MIN",
    "EPS2D",
    "ProjectedGaussians",
    "quat_to_rotmat",
    "covariance_3d",
    "project_gaussians",
]

#: Pairs with alpha below this are skipped (gsplat's 1/255); Gaussians with lower opacity culled.
ALPHA_MIN = 1.0 / 255.0
#: Alpha is clamped to at most this value, so one Gaussian never makes a pixel fully opaque.
ALPHA_MAX = 0.99
#: A pixel stops compositing when its transmittance would fall to or below this value.
TRANSMITTANCE_MIN = 1e-4
#: Low-pass filter (pixels²) added to the diagonal of every 2D covariance.
EPS2D = 0.3
#: Field-of-view factor for the Jacobian clamp (gsplat: 1.3x the half-FOV tangent).
FOV_CLAMP = 1.3
_QUAT_EPS = 1e-24


@dataclass
class ProjectedGaussians:
    """Camera–Gaussian pairs that survived culling (packed: one row per pair, V rows).

    Rows are ordered by (camera, Gaussian index).

    Attributes:
        cam_ids: [V] int64 camera of each pair.
        gauss_ids: [V] int64 Gaussian of each pair.
        means2d: [V, 2] pixel coordinates (u, v) of the projected centres.
        conics: [V, 3] inverse 2D covariance (a, b, c): ``[[a, b], [b, c]]`` (1/pixels²).
        depths: [V] camera-z depth of the centres (metres).
        extents: [V, 2] half-width and half-height (pixels) of the axis-aligned box outside
            which alpha < ALPHA_MIN (opacity-aware, exact for the ellipse, plus a hair of slack
            for rounding); no gradient.
    """

    cam_ids: torch.Tensor
    gauss_ids: torch.Tensor
    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    extents: torch.Tensor

    def __len__(self) -> int:
        return int(self.cam_ids.numel())


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices from (not necessarily unit) quaternions.

    Args:
        quats: [..., 4] quaternions (w, x, y, z). Normalised with an epsilon: a zero quaternion
            gives the identity and a finite gradient.

    Returns:
        [..., 3, 3] rotation matrices.
    """
    q = quats * torch.rsqrt((quats * quats).sum(-1, keepdim=True) + _QUAT_EPS)
    w, x, y, z = q.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    rows = [
        1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
        2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
        2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy),
    ]  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(*quats.shape[:-1], 3, 3)


def covariance_3d(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """World-frame covariance ``R diag(s²) Rᵀ``.

    Args:
        quats: [N, 4] quaternions (w, x, y, z).
        scales: [N, 3] standard deviations along the Gaussian's axes (metres).

    Returns:
        [N, 3, 3] covariances (metres²).
    """
    m = quat_to_rotmat(quats) * scales[:, None, :]
    return m @ m.transpose(-1, -2)


def _opacity_radius(opacities: torch.Tensor) -> torch.Tensor:
    """Mahalanobis radius where ``opacity * exp(-r²/2)`` falls to ALPHA_MIN (0 if never above)."""
    ratio = (opacities.detach() / ALPHA_MIN).clamp_min(1.0)
    return torch.sqrt(2.0 * torch.log(ratio))


def _jacobian_terms(x, y, zc, fx, fy, cx, cy, width, height):
    """x/z and y/z clamped to 1.3x the field of view (per side, principal-point aware)."""
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lim_xp = (width - cx) / fx + (FOV_CLAMP - 1.0) * tan_x
    lim_xn = cx / fx + (FOV_CLAMP - 1.0) * tan_x
    lim_yp = (height - cy) / fy + (FOV_CLAMP - 1.0) * tan_y
    lim_yn = cy / fy + (FOV_CLAMP - 1.0) * tan_y
    tx = torch.minimum(torch.maximum(x / zc, -lim_xn), lim_xp)
    ty = torch.minimum(torch.maximum(y / zc, -lim_yn), lim_yp)
    return tx, ty


def _box_inside(u, v, ex, ey, width: int, height: int) -> torch.Tensor:
    """Whether a box of half-size (ex, ey) around (u, v) contains a pixel centre of the image."""
    return (u + ex >= 0.5) & (u - ex <= width - 0.5) & (v + ey >= 0.5) & (v - ey <= height - 0.5)


def project_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    near: float,
    far: float,
    eps2d: float = EPS2D,
) -> ProjectedGaussians:
    """Project Gaussians into every camera and keep the pairs that can touch a pixel.

    Culling (no gradient): camera z outside [near, far], opacity < ALPHA_MIN, non-finite
    projection, or an alpha >= ALPHA_MIN box with no pixel centre inside the image. A cheap
    conservative box (from the largest scale and the Jacobian's Frobenius norm) is tested on all
    C x N pairs first; the exact covariance is computed only for the survivors. Differentiable
    in means, quats and scales.

    Args:
        means: [N, 3] centres, world frame (metres).
        quats: [N, 4] rotations (w, x, y, z), any norm.
        scales: [N, 3] axis standard deviations (metres).
        opacities: [N] opacities (culling and extents only; no gradient here).
        viewmats: [C, 4, 4] world→camera transforms.
        Ks: [C, 3, 3] intrinsics (pixels; skew ignored).
        width: image width (pixels).
        height: image height (pixels).
        near: pairs with camera z < near are culled (metres).
        far: pairs with camera z > far are culled (metres).
        eps2d: low-pass added to the 2D covariance diagonal (pixels²).

    Returns:
        :class:`ProjectedGaussians` with V <= C * N rows.
    """
    rot_w = viewmats[:, :3, :3]  # [C, 3, 3]
    t_w = viewmats[:, :3, 3]  # [C, 3]
    p_cam = torch.einsum("cij,nj->cni", rot_w, means) + t_w[:, None, :]  # [C, N, 3]
    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]  # [C, 1]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    z_floor = max(near, 1e-6)  # depths used in divisions: culled pairs stay finite
    intr = (fx, fy, cx, cy)
    r = _opacity_radius(opacities.detach())[None, :]  # [1, N]
    cam_ids, gauss_ids = _coarse_cull(
        p_cam.detach(), scales.detach(), r, intr, width, height, near, far, z_floor, eps2d
    )

    p = p_cam[cam_ids, gauss_ids]  # [V, 3]
    x, y, z = p.unbind(-1)
    zc = z.clamp_min(z_floor)
    fx, fy, cx, cy = fx[cam_ids, 0], fy[cam_ids, 0], cx[cam_ids, 0], cy[cam_ids, 0]
    u = fx * (x / zc) + cx
    v = fy * (y / zc) + cy
    tx, ty = _jacobian_terms(x, y, zc, fx, fy, cx, cy, width, height)
    zero = torch.zeros_like(zc)
    jac = torch.stack([fx / zc, zero, -fx * tx / zc, zero, fy / zc, -fy * ty / zc], dim=-1).reshape(
        -1, 2, 3
    )  # [V, 2, 3]
    # (J W) M with M = R diag(s): Σ' = (J W M)(J W M)ᵀ, positive semi-definite by construction.
    m = quat_to_rotmat(quats[gauss_ids]) * scales[gauss_ids, None, :]  # [V, 3, 3]
    conics, a, c = _conics((jac @ rot_w[cam_ids]) @ m, eps2d)
    means2d = torch.stack([u, v], dim=-1)

    with torch.no_grad():
        rr = r[0, gauss_ids]
        # Tight half-extents of the alpha >= ALPHA_MIN ellipse, plus a little slack for rounding.
        ex = rr * torch.sqrt(a) * (1.0 + 1e-6) + 1e-3
        ey = rr * torch.sqrt(c) * (1.0 + 1e-6) + 1e-3
        extents = torch.stack([ex, ey], dim=-1)
        ok = _box_inside(u, v, ex, ey, width, height)
        ok &= torch.isfinite(conics).all(-1) & torch.isfinite(extents).all(-1)
        sel = torch.nonzero(ok).squeeze(1)
    if sel.numel() == ok.numel():
        return ProjectedGaussians(cam_ids, gauss_ids, means2d, conics, z, extents)
    return ProjectedGaussians(
        cam_ids[sel], gauss_ids[sel], means2d[sel], conics[sel], z[sel], extents[sel]
    )


def pixel_centres(width: int, height: int, dtype: torch.dtype, device) -> torch.Tensor:
    """Pixel centres [H, W, 2] as (u, v) = (i + 0.5, j + 0.5)."""
    us = torch.arange(width, dtype=dtype, device=device) + 0.5
    vs = torch.arange(height, dtype=dtype, device=device) + 0.5
    return torch.stack(torch.meshgrid(us, vs, indexing="xy"), dim=-1)


def log_alpha_cut() -> float:
    """log(TRANSMITTANCE_MIN), the log-space termination threshold."""
    return math.log(TRANSMITTANCE_MIN)


@torch.no_grad()
def _coarse_cull(p_cam, scales, r, intr, width, height, near, far, z_floor, eps2d):
    """(camera, Gaussian) pairs that may touch a pixel: a conservative box on all C x N pairs.

    Args:
        p_cam: [C, N, 3] centres in each camera, metres. scales: [N, 3]. r: [1, N] the
            opacity's alpha >= ALPHA_MIN radius in standard deviations. intr: ``(fx, fy, cx,
            cy)`` each [C, 1], pixels.

    Returns:
        ``(cam_ids [V], gauss_ids [V])`` int64.
    """
    fx, fy, cx, cy = intr
    x, y, z = p_cam.unbind(-1)
    zc = z.clamp_min(z_floor)
    s_max = scales.abs().amax(-1)[None, :]  # [1, N]
    tx, ty = _jacobian_terms(x, y, zc, fx, fy, cx, cy, width, height)
    j_norm2 = (fx * fx * (1 + tx * tx) + fy * fy * (1 + ty * ty)) / (zc * zc)
    bound = r * torch.sqrt(s_max * s_max * j_norm2 + eps2d) * 1.01 + 1.0
    u0, v0 = fx * (x / zc) + cx, fy * (y / zc) + cy
    keep = (z >= near) & (z <= far) & (r > 0) & _box_inside(u0, v0, bound, bound, width, height)
    keep &= torch.isfinite(u0) & torch.isfinite(v0) & torch.isfinite(bound)
    return torch.nonzero(keep, as_tuple=True)


def _conics(jwm: torch.Tensor, eps2d: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Inverse 2D covariances of ``Σ' = (JWM)(JWM)ᵀ + eps2d I``.

    Args:
        jwm: [V, 2, 3] projection Jacobian × world→camera rotation × R diag(s).
        eps2d: the low-pass added to the diagonal, pixels².

    Returns:
        ``(conics [V, 3] = (c, -b, a) / det, a [V], c [V])`` with ``a``, ``c`` the diagonal of
        Σ' (pixels²).
    """
    r0, r1 = jwm[:, 0, :], jwm[:, 1, :]
    a0 = (r0 * r0).sum(-1)
    b = (r0 * r1).sum(-1)
    c0 = (r1 * r1).sum(-1)
    # Cauchy–Binet: det(JWM (JWM)ᵀ) = sum of the squared 2x2 minors (never negative).
    minors = torch.stack(
        [
            r0[:, 0] * r1[:, 1] - r0[:, 1] * r1[:, 0],
            r0[:, 0] * r1[:, 2] - r0[:, 2] * r1[:, 0],
            r0[:, 1] * r1[:, 2] - r0[:, 2] * r1[:, 1],
        ],
        dim=-1,
    )
    det = (minors * minors).sum(-1) + eps2d * (a0 + c0) + eps2d * eps2d
    a = a0 + eps2d
    c = c0 + eps2d
    return torch.stack([c / det, -b / det, a / det], dim=-1), a, c
