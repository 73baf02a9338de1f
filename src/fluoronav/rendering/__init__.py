"""DRR rendering: line integrals through CT volumes and through the CM, batched, CPU and CUDA."""

from fluoronav.rendering.ct import CTRenderer, render_line_integrals

__all__ = ["CTRenderer", "render_line_integrals"]
