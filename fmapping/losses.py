"""Mapping losses: photometric, multi-view warping (photo-consistency), depth.

Conventions follow :mod:`fmapping.geometry` and :mod:`fmapping.camera`: poses are
camera-to-world 4x4, rays have z-normalised directions so a rendered "depth" ``t``
is the camera z of the point ``o + t * d``; images are float tensors (V, H, W, C)
in [0, 1]; pixel centres are integer coordinates.

The warping loss is the load-bearing geometric signal of RGB-only mapping: a
pixel's rendered depth is lifted to 3D, projected into the other frames of the
window, and the colour patches there are compared with the patch around the
pixel in its own frame. Gradients reach the depth (hence the field) through the
bilinear image sampling, and the poses through the projection. Views where the
point falls outside the image or behind the camera are masked; occlusions are
handled robustly by averaging only the best fraction of the views (as in
multi-view stereo), and optionally by a depth test against rendered depth maps.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as F
from torch import Tensor

from fmapping.camera import PinholeCamera
from fmapping.geometry import se3_inverse


def photometric_loss(pred: Tensor, target: Tensor, kind: str = "l2", delta: float = 0.1,
                     weight: Optional[Tensor] = None) -> Tensor:
    """Mean colour error: ``"l2"`` (squared error) or ``"huber"`` (quadratic below ``delta``).

    ``weight`` (N,) optionally weighs rays; the result is the weighted mean.
    """
    if pred.shape != target.shape:
        raise ValueError(f"photometric_loss: shapes differ, pred {tuple(pred.shape)} vs target {tuple(target.shape)}")
    if kind == "l2":
        err = (pred - target) ** 2
    elif kind == "huber":
        err = F.huber_loss(pred, target, reduction="none", delta=delta)
    elif kind == "l1":
        err = (pred - target).abs()
    else:
        raise ValueError(f"photometric_loss: unknown kind {kind!r} (l2, huber, l1)")
    err = err.mean(-1) if err.dim() > 1 else err
    if weight is None:
        return err.mean()
    return (err * weight).sum() / weight.sum().clamp_min(1e-8)


def depth_l1_loss(pred: Tensor, target: Tensor) -> Tensor:
    """Mean |pred - target| over pixels with valid (> 0, finite) target depth; 0 when none."""
    valid = torch.isfinite(target) & (target > 0)
    if not bool(valid.any()):
        return pred.sum() * 0.0
    return (pred[valid] - target[valid]).abs().mean()


def expected_depth_l1(weights: Tensor, t: Tensor, acc: Tensor, t_far: Tensor, target: Tensor) -> Tensor:
    """Expected |termination depth - target| of the rendering distribution (mean over valid rays).

    ``sum_i w_i |t_i - z| + (1 - acc) |t_far - z|``: unreached mass counts as ending at the
    ray's far bound. Unlike ``|sum w t - z|`` every sample gets a direct signal (weight in front
    of or behind the surface is penalised by its distance), so a surface that first formed at
    the wrong depth is removed instead of being dragged slowly. Rays with invalid target
    (<= 0 or non-finite) are ignored; 0 when none is valid.
    """
    valid = torch.isfinite(target) & (target > 0)
    if not bool(valid.any()):
        return weights.sum() * 0.0
    z = target[valid, None]
    per = (weights[valid] * (t[valid] - z).abs()).sum(-1) + (1 - acc[valid]) * (t_far[valid] - z[:, 0]).abs()
    return per.mean()


def sparse_depth_loss(weights: Tensor, t: Tensor, acc: Tensor, t_far: Tensor, target: Tensor, point_weight: Tensor,
                      cap: float = 0.5) -> Tensor:
    """Pull each ray's termination distribution onto a sparse (triangulated) depth ``target``.

    Per ray the expected *relative* distance of termination from the target,
    ``sum_i w_i |t_i - z| / z + (1 - acc) |t_far - z| / z`` (unreached mass ends at the far bound),
    so weight in front of the point (floaters) and behind it is penalised by how far off it is,
    and the term does not depend on the world's unit (monocular maps have none). Each ray's
    value ``x`` enters as ``x / (1 + x / cap)`` (bounded by ``cap``, its pull fading with the
    error): a badly triangulated point cannot drag the surface far, yet an empty ray still
    feels it. Each ray's value is scaled by ``point_weight`` (the point's confidence) and summed over
    the valid rays, divided by their *number* (not by the weights' sum: points that are all doubtful
    pull weakly, instead of being renormalised to full strength); 0 when no ray is valid.
    """
    valid = torch.isfinite(target) & (target > 0) & (point_weight > 0)
    if not bool(valid.any()):
        return weights.sum() * 0.0
    z = target[valid, None]
    per = (weights[valid] * (t[valid] - z).abs()).sum(-1) / z[:, 0] \
        + (1 - acc[valid]) * (t_far[valid] - z[:, 0]).abs() / z[:, 0]
    w = point_weight[valid]
    return (per / (1 + per / cap) * w).sum() / w.numel()


def distortion_loss(weights: Tensor, t: Tensor, t_near: Tensor, t_far: Tensor) -> Tensor:
    """Mip-NeRF 360's distortion loss: how spread out each ray's termination distribution is.

    With samples at (sorted) ``t`` rescaled to ``s = (t - near) / (far - near)`` in [0, 1] and
    interval lengths ``delta`` (gaps between samples; the last one reaches ``far``),
    ``sum_ij w_i w_j |s_i - s_j| + 1/3 sum_i w_i^2 delta_i`` per ray; mean over rays. It is
    smallest when the weight sits in one short interval, so it removes the semi-transparent
    fog and the "sheets" spread along a ray that colour alone cannot pin down on weak texture.
    The double sum is computed in O(samples) with prefix sums:
    ``sum_ij w_i w_j |s_i - s_j| = 2 sum_i w_i (s_i W_<i - (ws)_<i)``.
    """
    span = (t_far - t_near).clamp_min(1e-6)[:, None]
    s = (t - t_near[:, None]) / span
    delta = torch.diff(s, dim=-1, append=torch.ones_like(s[:, :1])).clamp_min(0)
    w_before = torch.cumsum(weights, -1) - weights
    ws_before = torch.cumsum(weights * s, -1) - weights * s
    inter = 2 * (weights * (s * w_before - ws_before)).sum(-1)
    intra = (weights.pow(2) * delta).sum(-1) / 3
    return (inter + intra).mean()


def gaussian_blur(images: Tensor, sigma: float) -> Tensor:
    """(V, H, W, C) images smoothed by a separable Gaussian of ``sigma`` px (radius 3 sigma, borders
    replicated); ``sigma`` <= 0 returns them unchanged."""
    if sigma <= 0:
        return images
    r = max(1, int(math.ceil(3 * sigma)))
    x = torch.arange(-r, r + 1, dtype=images.dtype, device=images.device)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    c = images.shape[-1]
    y = images.permute(0, 3, 1, 2)
    y = F.conv2d(F.pad(y, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    y = F.conv2d(F.pad(y, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)
    return y.permute(0, 2, 3, 1).contiguous()


def patch_offsets(radius: int = 1, dilation: float = 1.0, device=None, dtype=torch.float32) -> Tensor:
    """Pixel offsets (P, 2) of a (2r+1)^2 square patch, spaced ``dilation`` pixels."""
    r = torch.arange(-radius, radius + 1, device=device, dtype=dtype) * dilation
    dv, du = torch.meshgrid(r, r, indexing="ij")
    return torch.stack([du.reshape(-1), dv.reshape(-1)], -1)


def sample_views(images: Tensor, uv: Tensor, views: Optional[Tensor] = None) -> Tensor:
    """Bilinear lookup in a stack of images.

    images (V, H, W, C); uv (V, M, 2) pixel coordinates per view -> (V, M, C),
    border-clamped (callers mask out-of-view points themselves). Differentiable
    w.r.t. ``uv`` (and the images). ``views`` (V,) long: view ``j`` of ``uv`` is looked up in
    ``images[views[j]]`` of a larger stack, without copying those images out of it (``images[views]``
    would copy them: 30 MB for 8 views of 640 x 480).
    """
    if views is not None:
        return torch.stack([sample_views(images[i:i + 1], uv[j:j + 1])[0] for j, i in enumerate(views.tolist())])
    v, h, w, c = images.shape
    grid = torch.stack([(uv[..., 0] + 0.5) / w * 2 - 1, (uv[..., 1] + 0.5) / h * 2 - 1], -1)
    out = F.grid_sample(images.permute(0, 3, 1, 2), grid[:, :, None].to(images.dtype), mode="bilinear",
                        padding_mode="border", align_corners=False)  # (V, C, M, 1)
    return out[..., 0].permute(0, 2, 1)


def sample_frames(images: Tensor, frame: Tensor, uv: Tensor) -> Tensor:
    """Bilinear lookup of point ``i`` in image ``frame[i]``: images (V,H,W,C), frame (N,), uv (N,P,2) -> (N,P,C)."""
    n, p = uv.shape[:2]
    vcount = images.shape[0]
    out = torch.zeros(n, p, images.shape[-1], dtype=images.dtype, device=images.device)
    # group by frame so every image is read once (V is small: the window)
    for f in torch.unique(frame).tolist():
        sel = (frame == f).nonzero(as_tuple=True)[0]
        if not 0 <= f < vcount:
            raise ValueError(f"sample_frames: frame index {f} outside 0..{vcount - 1}")
        out[sel] = sample_views(images[f:f + 1], uv[sel].reshape(1, -1, 2))[0].reshape(len(sel), p, -1)
    return out


def view_angle_mask(points: Tensor, ray_dirs: Tensor, c2w: Tensor, max_angle_deg: float) -> Tensor:
    """(V, M) bool: view ``v`` (``c2w`` (V, 4, 4)) sees world point ``points`` (M, 3) along a direction within
    ``max_angle_deg`` of the point's own ray ``ray_dirs`` (M, 3, any length). A point seen from far around it
    is more likely hidden there, or shows another side: multi-view stereo compares views of similar direction."""
    d0 = torch.nn.functional.normalize(ray_dirs, dim=-1)
    dv = torch.nn.functional.normalize(points[None] - c2w[:, None, :3, 3], dim=-1)  # (V, M, 3)
    return (dv * d0[None]).sum(-1) >= math.cos(math.radians(max_angle_deg))


def project_patches(points: Tensor, src: Tensor, images: Tensor, c2w: Tensor, camera: PinholeCamera, radius: int = 1,
                    dilation: float = 1.0, min_z: float = 0.05, ray_dirs: Optional[Tensor] = None,
                    max_angle_deg: float = 0.0,
                    views: Optional[Tensor] = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """World points (M, 3) of frames ``src`` (M,) seen in every view ``images`` (V, H, W, C) /
    ``c2w`` (V, 4, 4): returns pixel coordinates uv (V, M, 2), camera z (V, M), the mask (V, M)
    of usable views (z > ``min_z``, the whole patch inside the image, not the point's own frame,
    and with ``ray_dirs`` (M, 3) and ``max_angle_deg`` > 0 within that angle of the point's ray, see
    :func:`view_angle_mask`) and the (2r+1)^2 patches around uv, offsets spaced ``dilation`` px (V, M, P, C).
    Differentiable w.r.t. the points, poses and images (masked entries hold clamped samples). ``views`` (V,):
    the views are ``images[views]`` of a larger stack (:func:`sample_views`), ``src`` indexes them."""
    v = images.shape[0] if views is None else len(views)
    w2c = se3_inverse(c2w)  # (V, 4, 4)
    cam_pts = torch.einsum("vij,mj->vmi", w2c[:, :3, :3], points) + w2c[:, None, :3, 3]  # (V, M, 3)
    z = cam_pts[..., 2]
    zs = torch.where(z.abs() < 1e-6, torch.full_like(z, 1e-6), z)
    uv = torch.stack([camera.fx * cam_pts[..., 0] / zs + camera.cx, camera.fy * cam_pts[..., 1] / zs + camera.cy], -1)
    off = patch_offsets(radius, dilation, device=points.device, dtype=uv.dtype)  # (P, 2)
    mask = (z > min_z) & camera.in_image(uv, margin=radius * dilation)
    mask &= src[None, :] != torch.arange(v, device=points.device)[:, None]
    if ray_dirs is not None and max_angle_deg > 0:
        mask &= view_angle_mask(points.detach(), ray_dirs.detach(), c2w.detach(), max_angle_deg)
    m, p = uv.shape[1], off.shape[0]
    patches = sample_views(images, (uv[:, :, None, :] + off).reshape(v, m * p, 2), views).reshape(v, m, p, -1)
    return uv, z, mask, patches


@dataclass
class WarpResult:
    loss: Tensor  # scalar
    per_ray: Tensor  # (N,) robust per-ray error (0 where no valid view)
    valid_rays: Tensor  # (N,) bool: at least ``min_views`` views passed the masks
    errors: Tensor  # (N, V) per-view patch error (inf where masked)
    mask: Tensor  # (N, V) bool: view usable for the ray


def warping_loss(
    origins: Tensor,
    dirs: Tensor,
    depth: Tensor,
    uv: Tensor,
    src: Tensor,
    images: Tensor,
    c2w: Tensor,
    camera: PinholeCamera,
    radius: int = 1,
    dilation: float = 1.0,
    keep: float = 0.5,
    min_views: int = 1,
    min_z: float = 0.05,
    view_depths: Optional[Tensor] = None,
    occlusion_tol: float = 0.1,
    ref_colors: Optional[Tensor] = None,
    ray_weight: Optional[Tensor] = None,
    max_angle_deg: float = 0.0,
    views: Optional[Tensor] = None,
) -> WarpResult:
    """Multi-view photo-consistency of rendered depth.

    origins, dirs (N, 3): the world rays of the pixels (z-normalised dirs, as rendered);
    depth (N,): rendered depth along them; uv (N, 2) the pixels and src (N,) long the
    index of their frame in ``images`` (V, H, W, C) / ``c2w`` (V, 4, 4).

    For every ray and every other view: project ``x = o + depth * d``, sample a
    (2r+1)^2 patch (offsets spaced ``dilation`` px) there and compare it with the
    patch around ``uv`` in the source image (mean absolute difference over patch
    and channels). Masks: the source view itself, points with camera z < ``min_z``,
    patches not fully inside the image, and - when ``view_depths`` (V, H, W) rendered
    depth maps are given - points more than ``occlusion_tol`` (relative) behind the
    surface that view sees; with ``max_angle_deg`` > 0, views that see the point from farther than that
    angle off its ray (:func:`view_angle_mask`). The per-ray error is the mean of the lowest
    ``ceil(keep * valid)`` view errors (``keep=0`` -> the minimum); the loss is its mean
    over rays with at least ``min_views`` valid views (optionally weighted by ``ray_weight``).
    ``views`` (V,): the views are ``images[views]`` of a larger stack, read in place (:func:`sample_views`).
    """
    n = depth.shape[0]
    v = images.shape[0] if views is None else len(views)
    dev = depth.device
    if c2w.shape != (v, 4, 4):
        raise ValueError(f"warping_loss: c2w must be ({v}, 4, 4) for {v} images, got {tuple(c2w.shape)}")
    pts = origins + dirs * depth[:, None]  # (N, 3) world
    # target patches tgt (V, N, P, C)
    uv_t, z, mask, tgt = project_patches(pts, src, images, c2w, camera, radius, dilation, min_z, dirs, max_angle_deg,
                                         views)
    if view_depths is not None:
        d_at = sample_views(view_depths[..., None], uv_t.detach())[..., 0]  # (V, N)
        mask &= ~((d_at > 0) & (z.detach() > d_at * (1 + occlusion_tol)))
    if ref_colors is None:
        off = patch_offsets(radius, dilation, device=dev, dtype=uv_t.dtype)  # (P, 2)
        ref_colors = sample_frames(images, src if views is None else views[src], uv[:, None, :] + off)  # (N, P, C)
    err = (tgt - ref_colors[None]).abs().mean((-1, -2))  # (V, N)
    err = err.T  # (N, V)
    mask = mask.T
    big = torch.finfo(err.dtype).max
    e_masked = torch.where(mask, err, torch.full_like(err, big))
    nvalid = mask.sum(-1)
    k = torch.clamp(torch.ceil(keep * nvalid.to(err.dtype)).long(), min=1)
    order = torch.argsort(e_masked.detach(), dim=-1)
    rank = torch.empty_like(order)
    rank.scatter_(1, order, torch.arange(v, device=dev).expand(n, v).contiguous())
    use = mask & (rank < k[:, None])
    per_ray = (torch.where(use, err, torch.zeros_like(err))).sum(-1) / k.to(err.dtype)
    valid = nvalid >= max(1, min_views)
    per_ray = torch.where(valid, per_ray, torch.zeros_like(per_ray))
    if ray_weight is not None:
        wv = ray_weight * valid.to(err.dtype)
        loss = (per_ray * wv).sum() / wv.sum().clamp_min(1e-8)
    else:
        loss = per_ray.sum() / valid.sum().clamp_min(1)
    return WarpResult(loss=loss, per_ray=per_ray, valid_rays=valid,
                      errors=torch.where(mask, err.detach(), torch.full_like(err, math.inf)), mask=mask)


def sample_consistency_cost(
    points: Tensor,
    ref_colors: Tensor,
    src: Tensor,
    images: Tensor,
    c2w: Tensor,
    camera: PinholeCamera,
    radius: int = 1,
    dilation: float = 1.0,
    keep: float = 0.5,
    min_z: float = 0.05,
    no_view_cost: float = 0.0,
    ray_dirs: Optional[Tensor] = None,
    max_angle_deg: float = 0.0,
    views: Optional[Tensor] = None,
) -> tuple[Tensor, Tensor]:
    """Photo-consistency cost of every ray sample (a plane-sweep style cost volume).

    points (N, S, 3) world samples of N rays from frames ``src`` (N,);
    ref_colors (N, P, C) the source patch of each ray. Each sample is projected
    into every other view; the cost is the robust mean (best ``keep`` fraction) of
    patch errors. Returns cost (N, S) and the number of valid views (N, S).
    Samples seen by no other view get ``no_view_cost``. With ``ray_dirs`` (N, 3) and ``max_angle_deg`` > 0,
    only views within that angle of the ray count (:func:`view_angle_mask`). Not differentiable by design
    (used as a fixed per-sample target for the rendering weights). ``views`` (V,): the views are
    ``images[views]`` of a larger stack, read in place (:func:`sample_views`).
    """
    with torch.no_grad():
        n, s, _ = points.shape
        v = images.shape[0] if views is None else len(views)
        dev = points.device
        dirs = None if ray_dirs is None else ray_dirs[:, None].expand(n, s, 3).reshape(-1, 3)
        _, _, mask, tgt = project_patches(points.reshape(-1, 3), src[:, None].expand(n, s).reshape(-1), images, c2w,
                                          camera, radius, dilation, min_z, dirs, max_angle_deg, views)  # (V, NS)
        tgt = tgt.reshape(v, n, s, tgt.shape[2], -1)
        err = (tgt - ref_colors[None, :, None]).abs().mean((-1, -2)).reshape(v, -1).T  # (NS, V)
        mask = mask.T
        nvalid = mask.sum(-1)
        k = torch.clamp(torch.ceil(keep * nvalid.to(err.dtype)).long(), min=1)
        if keep >= 1.0:  # plain mean over the valid views: no sort needed
            cost = torch.where(mask, err, torch.zeros_like(err)).sum(-1) / k.to(err.dtype)
        else:
            srt, _ = torch.sort(torch.where(mask, err, torch.full_like(err, math.inf)), dim=-1)
            use = torch.arange(v, device=dev)[None, :] < k[:, None]
            srt = torch.where(use & torch.isfinite(srt), srt, torch.zeros_like(srt))
            cost = srt.sum(-1) / k.to(err.dtype)
        cost = torch.where(nvalid > 0, cost, torch.full_like(cost, no_view_cost))
        return cost.reshape(n, s), nvalid.reshape(n, s)
