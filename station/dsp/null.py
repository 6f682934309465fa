"""Where the trims null the ripple: one definition for the truth and the estimate.

The paper sets the offsets to null the 1st harmonic and then the gain split
(at a constant gain sum) to null the 2nd. A real split cannot null a complex
H2 whose quadrature part it does not reach, and H2 may depend on the offsets
too, so "least |H1|² + |H2|²" would pull the offsets off H1's null to shave
H2's unreachable part: a different optimum, by as much as 12 mA on a
saturating unit measured near, not at, its null. The station holds to the
paper's order: H1 = 0 exactly, then the least |H2| among the trims that keep it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray


def h1_then_h2_null(
    h1: complex, h2: complex, jac1: ArrayLike, jac2: ArrayLike
) -> NDArray[np.float64]:
    """Step Δ in (offset A, offset B, split) under the affine maps H_k + J_k·Δ.

    H1 + J1·Δ = 0 is two real equations in three unknowns: the line
    Δp + t·n. Along it H2 is complex-affine in t, minimised at
    t* = −Re(conj(J2·n)·(H2 + J2·Δp)) / |J2·n|², with Δp the smallest step
    onto H1's null and n the direction J1 does not see.
    """
    j1 = np.asarray(jac1, dtype=np.complex128)
    j2 = np.asarray(jac2, dtype=np.complex128)
    if j1.shape != (3,) or j2.shape != (3,):
        raise ValueError(f"need 3 slopes per harmonic, got {j1.shape} and {j2.shape}")
    a = np.vstack([j1.real, j1.imag])
    particular = np.linalg.lstsq(a, -np.array([h1.real, h1.imag]), rcond=None)[0]
    free = np.linalg.svd(a)[2][-1]
    g = complex(j2 @ free)
    r = complex(h2 + j2 @ particular)
    t = -(g.conjugate() * r).real / abs(g) ** 2 if abs(g) > 0 else 0.0
    return np.asarray(particular + t * free, dtype=np.float64)
