"""Compile fluoronav's CPU kernels into numba's on-disk cache: ``python -m fluoronav.cli.compile_kernels``.

``make`` runs this after it installs, so that the first command after an install (``fluoronav
demo`` among them) loads the kernels' machine code instead of compiling it (about 20 s on 2 cores).
Each kernel is compiled for the argument types its module passes (``compile_kernels`` of that
module); where the cache is already there it loads in a fraction of a second.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from fluoronav.manipulator import geometry
from fluoronav.registration import similarity
from fluoronav.rendering import cm, ct
from fluoronav.simulation import xray

#: each module's compile_kernels, in pipeline order
COMPILERS: tuple[Callable[[], None], ...] = (
    geometry.compile_kernels,
    ct.compile_kernels,
    cm.compile_kernels,
    xray.compile_kernels,
    similarity.compile_kernels,
)


def compile_all() -> float:
    """Compile (or load from the cache) every CPU kernel; returns the seconds it took."""
    t0 = time.perf_counter()
    for compile_kernels in COMPILERS:
        compile_kernels()
    return time.perf_counter() - t0


def main() -> None:
    seconds = compile_all()
    print(f"fluoronav: CPU kernels compiled or loaded from numba's cache in {seconds:.1f} s")


if __name__ == "__main__":
    main()
