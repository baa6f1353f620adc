"""Batched, differentiable weighted Procrustes (Kabsch with weights and the reflection fix).

Given source points p_i, target points q_i and weights w_i >= 0, it finds the rotation R and the
translation t minimising sum_i w_i ||R p_i + t - q_i||^2:

    c_p = sum_i w_i p_i / sum_i w_i          c_q = sum_i w_i q_i / sum_i w_i
    H   = sum_i w_i (p_i - c_p)(q_i - c_q)^T = U S V^T
    R   = V diag(1, 1, det(V U^T)) U^T       t = c_q - R c_p

The backward pass of ``torch.linalg.svd`` divides by s_i^2 - s_j^2 and returns inf/NaN as soon
as two singular values coincide (symmetric shapes, all weights ~0), although R itself depends
smoothly on H there. So in eager mode the rotation goes through :class:`_RotationFromCovariance`,
whose backward uses the polar-decomposition form of the derivative: its only denominators are
sums of signed singular values, s_i + s_j, which vanish only when H has rank <= 1, and are kept
away from zero. The forward pass is the same SVD in both modes, so a scripted model computes the
same R as the eager one.
"""

from __future__ import annotations

from typing import NamedTuple, Optional, Tuple

import numpy as np
import torch

_EPS = 1e-8


class ProcrustesResult(NamedTuple):
    """R: (B, 3, 3) rotations; t: (B, 3) translations, such that q ~ R p + t."""

    R: torch.Tensor
    t: torch.Tensor


def _rotation_and_svd(H: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """R = V diag(1, 1, d) U^T with d = sign(det(V U^T)); also returns U and the signed S."""
    U, S, Vh = torch.linalg.svd(H)
    V = Vh.transpose(-1, -2)
    det = torch.det(torch.matmul(V, U.transpose(-1, -2)))
    d = torch.where(det < 0, -torch.ones_like(det), torch.ones_like(det))
    ones = torch.ones_like(d)
    D = torch.stack([ones, ones, d], dim=-1)  # (B, 3)
    R = torch.matmul(V * D.unsqueeze(-2), U.transpose(-1, -2))
    return R, U, S * D


class _RotationFromCovariance(torch.autograd.Function):
    """R(H) with a backward pass that stays finite for repeated or zero singular values.

    With H = U S V^T and D the reflection fix, H^T = R P where P = U (D S) U^T is symmetric.
    Differentiating, skew(R^T dH^T) = (Omega P + P Omega) / 2 with dR = R Omega, which in the
    eigenbasis U of P gives Omega_ij = 2 M_ij / (l_i + l_j), l = D S. Transposing this linear map
    gives the gradient below.
    """

    @staticmethod
    def forward(ctx, H: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        R, U, lam = _rotation_and_svd(H)
        ctx.save_for_backward(R, U, lam)
        return R

    @staticmethod
    def backward(ctx, grad_R: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        R, U, lam = ctx.saved_tensors
        denom = lam.unsqueeze(-1) + lam.unsqueeze(-2)  # (B, 3, 3): l_i + l_j
        scale = torch.clamp(lam.abs().amax(dim=-1, keepdim=True), min=_EPS).unsqueeze(-1)
        floor = 1e-6 * scale
        # Keep |l_i + l_j| >= floor with its sign, so the gradient is finite on rank-deficient H.
        denom = torch.where(denom.abs() < floor, torch.where(denom < 0, -floor, floor), denom)
        A = U.transpose(-1, -2) @ R.transpose(-1, -2) @ grad_R @ U
        B = 2.0 * A / denom
        C = U @ (0.5 * (B - B.transpose(-1, -2))) @ U.transpose(-1, -2)
        return -(C @ R.transpose(-1, -2))


@torch.jit.unused
def _rotation_with_safe_grad(H: torch.Tensor) -> torch.Tensor:
    return _RotationFromCovariance.apply(H)


def rotation_from_covariance(H: torch.Tensor) -> torch.Tensor:
    """The proper rotation R maximising tr(R H), for a batch of 3x3 cross-covariances.

    Args:
        H: (B, 3, 3) cross-covariance sum_i w_i (p_i - c_p)(q_i - c_q)^T.
    Returns:
        (B, 3, 3) rotations with det = +1.
    """
    if torch.jit.is_scripting():
        R, _, _ = _rotation_and_svd(H)
        return R
    return _rotation_with_safe_grad(H)


def weighted_procrustes(p: torch.Tensor, q: torch.Tensor, w: Optional[torch.Tensor] = None, eps: float = 1e-8) -> ProcrustesResult:
    """Rigid transform minimising sum_i w_i ||R p_i + t - q_i||^2, batched.

    Args:
        p: (B, N, 3) source points.
        q: (B, N, 3) corresponding target points (q_i pairs with p_i).
        w: (B, N) non-negative weights; None means all ones.
        eps: floor of sum_i w_i, so that all-zero weights give no division by zero.
    Returns:
        ProcrustesResult with R (B, 3, 3) and t (B, 3).
    Raises:
        ValueError: on shapes that do not match the above.
    """
    if p.dim() != 3 or p.shape[-1] != 3:
        raise ValueError(f"p must have shape (B, N, 3), got {list(p.shape)}")
    if q.shape != p.shape:
        raise ValueError(f"q must have the shape of p {list(p.shape)}, got {list(q.shape)}")
    if w is None:
        w = torch.ones(p.shape[0], p.shape[1], dtype=p.dtype, device=p.device)
    elif w.shape != p.shape[:2]:
        raise ValueError(f"w must have shape {list(p.shape[:2])}, got {list(w.shape)}")
    w_sum = w.sum(dim=1, keepdim=True).clamp(min=eps)  # (B, 1)
    wn = (w / w_sum).unsqueeze(-1)  # (B, N, 1); sums to 1 unless all weights are ~0
    c_p = (wn * p).sum(dim=1)  # (B, 3)
    c_q = (wn * q).sum(dim=1)
    p_c = p - c_p.unsqueeze(1)
    q_c = q - c_q.unsqueeze(1)
    H = torch.matmul((wn * p_c).transpose(1, 2), q_c)  # (B, 3, 3); scaled by 1/sum w, same R
    R = rotation_from_covariance(H)
    t = c_q - torch.matmul(R, c_p.unsqueeze(-1)).squeeze(-1)
    return ProcrustesResult(R, t)


def rigid_fit(p: np.ndarray, q: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """The unweighted fit of :func:`weighted_procrustes` for one pair of float64 arrays, in NumPy:
    ICP's last step calls it once per estimate, where the batched autograd path costs more
    than the 3x3 SVD itself.

    Args:
        p: (N, 3) source points; q: (N, 3) the target points they pair with.
    Returns:
        R (3, 3) with det = +1, t (3,), minimising sum_i ||R p_i + t - q_i||^2.
    """
    c_p, c_q = p.mean(axis=0), q.mean(axis=0)
    H = (p - c_p).T @ (q - c_q) / len(p)
    U, _, Vh = np.linalg.svd(H)
    V = Vh.T
    d = -1.0 if np.linalg.det(V @ U.T) < 0 else 1.0
    R = (V * np.array([1.0, 1.0, d])) @ U.T
    return R, c_q - R @ c_p
