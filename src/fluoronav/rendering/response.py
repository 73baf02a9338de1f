"""Response of a −log X-ray image to a DRR's line integrals: a veil model.

An analytic DRR is linear in the line integral ``L``; a real −log image is not: scatter and veiling
glare add intensity that the object does not attenuate, and beam hardening lowers the effective μ of
thick metal. With a veil ``f`` (the fraction of the flat field that passes unattenuated) and a gain
``g`` (the image's μ over the DRR's):

    y = −ln((1 − f)·exp(−g·L) + f)

``f = 0`` is the linear DRR ``g·L``; ``y`` saturates at ``−ln f`` for thick objects. The CM registration
measures ``(g, f)`` per view on the CM's shaft (:func:`~fluoronav.detection.tube_profile.fit_tube_profile`).
"""

from __future__ import annotations

import torch

__all__ = ["veil_response"]


def veil_response(line_integral: torch.Tensor, gain: torch.Tensor, veil: torch.Tensor) -> torch.Tensor:
    """``−ln((1 − f)·exp(−g·L) + f)`` per view.

    Args:
        line_integral: (..., V, h, w) DRR line integrals L (≥ 0).
        gain: (V,) g > 0.
        veil: (V,) f in [0, 1).

    Returns:
        Tensor of ``line_integral``'s shape and dtype.
    """
    g = gain.to(line_integral)[:, None, None]
    f = veil.to(line_integral)[:, None, None]
    if line_integral.requires_grad and torch.is_grad_enabled():
        return -torch.log((1.0 - f) * torch.exp(-g * line_integral) + f)
    # in place on one new tensor: a registration calls this on every candidate image
    return (line_integral * -g).exp_().mul_(1.0 - f).add_(f).log_().neg_()
