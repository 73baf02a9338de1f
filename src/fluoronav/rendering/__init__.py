"""DRR rendering: line integrals through CT volumes and through the CM, batched, CPU and CUDA.

- :mod:`~fluoronav.rendering.ct`: DRRs of a voxel volume (∫ μ dl) for any number of cameras, a
  numba ray march with empty-space skipping on the CPU, torch on CUDA;
- :mod:`~fluoronav.rendering.cm`: analytic DRRs of the notched CM (μ · chord length through the
  solid) for batches of candidate poses and shapes × views;
- :mod:`~fluoronav.rendering.response`: the response of a −log X-ray image to a DRR (a veil model);
- :mod:`~fluoronav.rendering.reference`: an independent exact-traversal DRR for tests.

Each module with a numba kernel provides ``compile_kernels()`` (run at install by
``fluoronav.cli.compile_kernels``).
"""

from typing import TYPE_CHECKING

from fluoronav.lazy import lazy_face

if TYPE_CHECKING:
    from fluoronav.rendering.cm import CMRenderer
    from fluoronav.rendering.ct import DEFAULT_STEP_VOXELS, CTRenderer, mipmap_factors, render_line_integrals
    from fluoronav.rendering.reference import siddon_line_integrals
    from fluoronav.rendering.response import veil_response

__all__ = [
    "DEFAULT_STEP_VOXELS",  # default ray-march step, in units of the smallest voxel spacing
    "CMRenderer",  # analytic CM DRRs: (candidates B, views V, rows, cols) in one call
    "CTRenderer",  # DRRs of one μ volume (1/mm) for any number of cameras: (V, rows, cols)
    "mipmap_factors",  # per-axis volume downsampling (1 or 2) that suits a camera's pixel footprint
    "render_line_integrals",  # functional CT DRR: μ tensor, world_from_index, K, camera_from_world
    "siddon_line_integrals",  # float64 exact voxel traversal (Siddon/Jacobs), the tests' reference
    "veil_response",  # −ln((1 − f)·exp(−g·L) + f): a −log image's response to line integrals L
]

__getattr__, __dir__ = lazy_face(__name__)
