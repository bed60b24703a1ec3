"""The pipeline stages (see the README's pipeline table) and what they share: batch-element selection."""

from __future__ import annotations

import torch

__all__ = ["batch_mask"]


def batch_mask(mask: torch.Tensor | None, batch_size: int) -> torch.Tensor:
    """Select batch elements: ``None`` (all), a ``(B,)`` bool mask or ``(K,)`` integer indices.

    Used by the stages' masked ``reset``: only the selected elements restart.

    Shape: returns ``(B,)`` bool.

    Raises:
        TypeError: not a bool or integer tensor.
        ValueError: a bool mask of the wrong shape, or an index outside ``[0, B)``.
    """
    if mask is None:
        return torch.ones(batch_size, dtype=torch.bool)
    mask = torch.as_tensor(mask)
    if mask.dtype == torch.bool:
        if mask.shape != (batch_size,):
            raise ValueError(f"mask must have shape ({batch_size},), got {tuple(mask.shape)}")
        return mask
    if mask.is_floating_point() or mask.is_complex() or mask.ndim != 1:
        raise TypeError(f"mask must be a ({batch_size},) bool tensor or a 1-D tensor of batch indices, "
                        f"got {mask.dtype} {tuple(mask.shape)}")
    if mask.numel() and (int(mask.min()) < 0 or int(mask.max()) >= batch_size):
        raise ValueError(f"mask indices must be in [0, {batch_size}), got {mask.tolist()}")
    return torch.zeros(batch_size, dtype=torch.bool).index_fill_(0, mask.long(), True)
