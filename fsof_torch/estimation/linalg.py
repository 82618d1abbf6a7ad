"""Small batched linear algebra for the solvers, without a host read: symmetric positive definite
systems by Cholesky and two triangular solves, and the test of positive definiteness."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["spd_solve", "positive_definite"]


# Small symmetric positive definite systems by Cholesky and two triangular solves: on the CPU,
# torch's LU, Cholesky-solve, inverse and eigenvalue routines read a value back to the host inside
# (a workspace or error query), which the triangular solves and cholesky_ex do not.

def spd_solve(A: Tensor, b: Tensor) -> Tensor:
    """x with A x = b for symmetric positive definite A (B, P, P) and b (B, P, K).

    Where A is not positive definite the result is meaningless: NaN, inf or finite values
    (``cholesky_ex`` reports the failure in its status, which is not read here, and its factor is
    then not meaningful); tell such systems apart with :func:`positive_definite`, not by the
    result's finiteness."""
    L, _ = torch.linalg.cholesky_ex(A)
    return torch.linalg.solve_triangular(L.mT, torch.linalg.solve_triangular(L, b, upper=False), upper=True)


def positive_definite(A: Tensor, margin: float | Tensor = 0.0) -> Tensor:
    """(B,) bool: the smallest eigenvalue of symmetric A (B, P, P) exceeds ``margin``."""
    eye = torch.eye(A.shape[-1], dtype=A.dtype, device=A.device)
    _, info = torch.linalg.cholesky_ex(A - margin * eye)
    return info == 0
