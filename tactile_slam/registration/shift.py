"""Global in-plane shift between two touches by cross-correlation of their normal maps.

NormalFlow converges from starts within a fraction of the texture's scale; a touch moved
by several millimetres is outside that basin, and on a fine texture block-averaged levels
flatten the very signal that would guide it. The shift that best aligns the two contacts'
normal ``(x, y)`` maps is found globally instead, for every shift at once through FFTs:
the correlation of the maps (zero outside the contacts) divided by the contacts' overlap
at that shift, over shifts whose overlap is at least ``min_overlap`` of the largest. A
pure translation leaves the normals unchanged, so the peak sits at the true shift; tilts
and large rotations change the maps, so this is a start for a retry, not a pose.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def correlation_shift(ref_normals: torch.Tensor, ref_contact: torch.Tensor, tar_normals: torch.Tensor,
                      tar_contact: torch.Tensor, min_overlap: float = 0.2, factor: int = 2) -> torch.Tensor:
    """The pixel shift ``d`` that best aligns the target with the reference shifted by ``d``.

    Args:
        ref_normals, tar_normals: ``(B or 1, H, W, 3)`` and ``(B, H, W, 3)`` normal maps.
        ref_contact, tar_contact: ``(B or 1, H, W)`` and ``(B, H, W)`` bool contact masks.
            Pixels whose normal is not finite count as outside the contact.
        min_overlap: shifts whose contact overlap is below this fraction of the pair's
            largest overlap are not considered (their normalised correlation is noise).
        factor: the maps are averaged over ``factor x factor`` blocks first (the search
            costs ``factor^2`` times less; the shift comes out in steps of ``factor``
            pixels, well inside the basin of the coarse levels that the retry starts with).

    Returns:
        ``(B, 2)`` float64 ``(dx, dy)`` in pixels: a reference pixel ``u`` shows up at
        ``u + d`` in the target. Pairs whose contacts cannot overlap get ``(0, 0)``.
    """
    if not 0.0 < min_overlap <= 1.0:
        raise ValueError(f"min_overlap must be in (0, 1], got {min_overlap}")
    if isinstance(factor, bool) or not isinstance(factor, int) or factor < 1:
        raise ValueError(f"factor must be an integer >= 1, got {factor!r}")
    _check_maps(ref_normals, ref_contact, tar_normals, tar_contact)
    if len(tar_contact) == 0:
        return torch.zeros((0, 2), dtype=torch.float64, device=tar_contact.device)
    h, w = (n // factor for n in tar_contact.shape[-2:])
    size = (2 * h, 2 * w)  # zero padding: no wrap-around

    def spectra(normals: torch.Tensor, contact: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        xy = normals[..., :2].to(torch.float32).permute(0, 3, 1, 2)
        mask = (contact & torch.isfinite(xy).all(1)).to(torch.float32)[:, None]
        maps = torch.cat([torch.where(mask > 0, xy, 0.0), mask], 1)
        pooled = torch.fft.rfft2(F.avg_pool2d(maps, factor), s=size)  # (B, 3, ...): nx, ny, contact
        return pooled[:, :2], pooled[:, 2]

    (n_ref, m_ref), (n_tar, m_tar) = spectra(ref_normals, ref_contact), spectra(tar_normals, tar_contact)
    corr = torch.fft.irfft2((n_tar * n_ref.conj()).sum(1), s=size)  # (B, 2h, 2w), index = shift (dy, dx)
    overlap = torch.fft.irfft2(m_tar * m_ref.conj(), s=size)  # in blocks
    best = overlap.flatten(1).amax(1)
    usable = (overlap >= min_overlap * best[:, None, None]) & (overlap > 0.5)
    score = torch.where(usable, corr / overlap.clamp_min(1.0), -torch.inf)
    flat = score.flatten(1).argmax(1)
    dy, dx = flat // size[1], flat % size[1]
    dy = torch.where(dy >= h, dy - size[0], dy)
    dx = torch.where(dx >= w, dx - size[1], dx)
    shift = torch.stack([dx, dy], 1).to(torch.float64) * factor
    return torch.where((best > 0.5)[:, None], shift, torch.zeros_like(shift))


def _check_maps(ref_normals: torch.Tensor, ref_contact: torch.Tensor, tar_normals: torch.Tensor,
                tar_contact: torch.Tensor) -> None:
    """Shapes of :func:`correlation_shift`'s maps, with a clear error."""
    for normals, contact, what in ((ref_normals, ref_contact, "reference"), (tar_normals, tar_contact, "target")):
        if normals.ndim != 4 or normals.shape[-1] != 3 or tuple(contact.shape) != tuple(normals.shape[:3]):
            raise ValueError(f"{what}: need (B, H, W, 3) normals and (B, H, W) contact masks, got "
                             f"{tuple(normals.shape)} and {tuple(contact.shape)}")
    if ref_normals.shape[1:] != tar_normals.shape[1:] or len(ref_normals) not in (1, len(tar_normals)):
        raise ValueError(f"reference maps {tuple(ref_normals.shape)} do not fit target maps "
                         f"{tuple(tar_normals.shape)} (same image size, batch 1 or the targets')")
