"""A small dense pure-torch Gaussian splatting function for the Img2Occ tests.

Same signature and result fields as ``renderworld.splat.rasterize``; a stand-in used before the
splat branch is merged and as an independent cross-check after. Every (pixel, Gaussian) pair
is evaluated, so keep images and Gaussian counts small.
"""

from __future__ import annotations

from typing import NamedTuple

import torch


class DenseResult(NamedTuple):
    features: torch.Tensor  # [C, H, W, D]
    depth: torch.Tensor  # [C, H, W]
    alpha: torch.Tensor  # [C, H, W]


def _quat_to_mat(q: torch.Tensor) -> torch.Tensor:
    q = q / torch.sqrt((q * q).sum(-1, keepdim=True) + 1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).view(*q.shape[:-1], 3, 3)  # fmt: skip


def dense_rasterize(
    means, quats, scales, opacities, features, viewmats, Ks, width, height,
    near=0.01, far=1e10, backend="auto",
) -> DenseResult:  # fmt: skip
    """Render features, expected camera-z depth and alpha at pixel centres (dense)."""
    del backend
    dev, dt = means.device, means.dtype
    d = features.shape[1]
    rot = _quat_to_mat(quats)
    cov = rot @ torch.diag_embed(scales * scales) @ rot.transpose(-1, -2)  # [N, 3, 3]
    jj, ii = torch.meshgrid(
        torch.arange(height, device=dev, dtype=dt),
        torch.arange(width, device=dev, dtype=dt),
        indexing="ij",
    )
    pix = torch.stack([ii + 0.5, jj + 0.5], -1).view(-1, 2)  # [P, 2]
    out_f, out_d, out_a = [], [], []
    for c in range(viewmats.shape[0]):
        r, t, k = viewmats[c, :3, :3], viewmats[c, :3, 3], Ks[c]
        pc = means @ r.T + t
        z = pc[:, 2]
        fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
        zc = z.clamp_min(near)
        u = fx * pc[:, 0] / zc + cx
        v = fy * pc[:, 1] / zc + cy
        keep = (z > near) & (z < far)  # no image-box culling: near Gaussians cover the image
        idx = torch.nonzero(keep.detach())[:, 0]
        if idx.numel() == 0:
            zero = (means.sum() + features.sum() + opacities.sum() + scales.sum()) * 0
            out_f.append(zero + torch.zeros(height * width, d, device=dev, dtype=dt))
            out_d.append(zero + torch.zeros(height * width, device=dev, dtype=dt))
            out_a.append(zero + torch.zeros(height * width, device=dev, dtype=dt))
            continue
        idx = idx[torch.argsort(z[idx].detach())]
        pcs, zs, us, vs = pc[idx], z[idx], u[idx], v[idx]
        lim_x = 1.3 * 0.5 * width / fx
        lim_y = 1.3 * 0.5 * height / fy
        tx = zs * (pcs[:, 0] / zs).clamp(-lim_x, lim_x)
        ty = zs * (pcs[:, 1] / zs).clamp(-lim_y, lim_y)
        zero = torch.zeros_like(zs)
        jac = torch.stack(
            [fx / zs, zero, -fx * tx / zs**2, zero, fy / zs, -fy * ty / zs**2], -1
        ).view(-1, 2, 3)
        cov_c = r @ cov[idx] @ r.T
        cov2 = jac @ cov_c @ jac.transpose(-1, -2) + 0.3 * torch.eye(2, device=dev, dtype=dt)
        a, b, cc = cov2[:, 0, 0], cov2[:, 0, 1], cov2[:, 1, 1]
        det = (a * cc - b * b).clamp_min(1e-12)
        dx = pix[:, None, 0] - us[None]
        dy = pix[:, None, 1] - vs[None]
        power = -0.5 * (cc * dx * dx - 2 * b * dx * dy + a * dy * dy) / det
        alpha = (opacities[idx][None] * torch.exp(power.clamp_max(0.0))).clamp_max(0.99)
        alpha = torch.where(alpha >= 1.0 / 255.0, alpha, torch.zeros_like(alpha))
        log_t = torch.cumsum(torch.log1p(-alpha), dim=1)
        log_t = torch.cat([torch.zeros_like(log_t[:, :1]), log_t[:, :-1]], dim=1)
        trans = torch.exp(log_t)
        w = alpha * trans * (trans > 1e-4).to(dt)
        acc = w.sum(1)
        out_f.append(w @ features[idx])
        out_a.append(acc)
        out_d.append(torch.where(acc > 1e-10, (w @ zs) / acc.clamp_min(1e-10), zero[:1] * 0))
    return DenseResult(
        torch.stack(out_f).view(-1, height, width, d),
        torch.stack(out_d).view(-1, height, width),
        torch.stack(out_a).view(-1, height, width),
    )
