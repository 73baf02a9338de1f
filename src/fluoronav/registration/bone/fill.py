"""Fill masked pixels from their surroundings (harmonic interpolation).

An occluding instrument left out of a similarity still reaches the pixels next to it through the
smoothing and Sobel filters of the gradient similarity: the metal's edge is the strongest gradient in
the image. Filling the masked pixels with the harmonic interpolation of the pixels around them (the
solution of Laplace's equation with the known pixels as boundary values) removes that edge, and the
filled values depend on the unmasked pixels only.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import spsolve

__all__ = ["harmonic_fill"]


def harmonic_fill(image: np.ndarray, fill: np.ndarray) -> np.ndarray:
    """Replace the pixels of ``image`` where ``fill`` is True by the discrete harmonic interpolation
    of the others (5-point Laplacian, zero normal derivative at the image border).

    Args:
        image: (H, W) float image.
        fill: (H, W) bool, True on the pixels to replace.

    Returns:
        (H, W) float64 copy; unchanged where ``fill`` is False. A linear ramp is reproduced exactly
        inside a filled region that does not touch the border. With nothing or everything to fill
        the image is returned as is (copied).

    Raises:
        ValueError: shapes differ or the image is not 2D.
    """
    img = np.asarray(image, dtype=np.float64)
    fill = np.asarray(fill, dtype=bool)
    if img.ndim != 2 or fill.shape != img.shape:
        raise ValueError(f"need a 2D image and a mask of its shape, got {img.shape} and {fill.shape}")
    n = int(fill.sum())
    if n == 0 or n == img.size:
        return img.copy()
    H, W = img.shape
    index = np.full((H, W), -1, dtype=np.int64)
    index[fill] = np.arange(n)
    pr, pc = np.nonzero(fill)
    p = index[pr, pc]
    diag = np.zeros(n)
    rhs = np.zeros(n)
    rows, cols = [], []
    for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        qr, qc = pr + dr, pc + dc
        inside = (qr >= 0) & (qr < H) & (qc >= 0) & (qc < W)
        pp, qr, qc = p[inside], qr[inside], qc[inside]
        diag[pp] += 1.0
        q = index[qr, qc]
        unknown = q >= 0
        rows.append(pp[unknown])
        cols.append(q[unknown])
        np.add.at(rhs, pp[~unknown], img[qr[~unknown], qc[~unknown]])
    r = np.concatenate([*rows, np.arange(n)])
    c = np.concatenate([*cols, np.arange(n)])
    v = np.concatenate([-np.ones(r.size - n), diag])
    A = sparse.csr_matrix((v, (r, c)), shape=(n, n))
    out = img.copy()
    out[fill] = spsolve(A, rhs)
    return out
