"""The ellipses of the route search in their unit-disc frames, where each one is the unit circle.

Every other module of the search (``roots``, ``arcs``, ``tangents``, ``graph``) works in these
coordinates: a tangent or a cut is a trigonometric polynomial in the angle round the unit circle.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.geometry import EllipseStack, FloatArray


@dataclass(frozen=True)
class Frames:
    """The scaled ellipses {z : ‖A z + b‖ ≤ 1} with their inverses, centres and reaches."""

    A: FloatArray
    b: FloatArray
    Ainv: FloatArray
    centers: FloatArray
    reach: FloatArray
    shape: FloatArray  # Q = A⁻¹A⁻ᵀ: the ellipse is {c + A⁻¹v : ‖v‖ ≤ 1}, support function √(nᵀQn)

    @classmethod
    def of(cls, stack: EllipseStack, scale: FloatArray) -> Frames:
        A = stack.A / scale[:, None, None]
        b = stack.b / scale[:, None]
        Ainv = np.linalg.inv(A)
        return cls(A=A, b=b, Ainv=Ainv, centers=-np.einsum("mij,mj->mi", Ainv, b), reach=stack.reach * scale,
                   shape=np.einsum("kij,klj->kil", Ainv, Ainv))

    def relative(self, i: FloatArray, j: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Ellipse j's centre c = Aᵢcⱼ + bᵢ (k, 2) and shape S = Aᵢ Qⱼ Aᵢᵀ (k, 2, 2) in i's unit-disc frame.

        Written out entry by entry (a batch of 2 × 2 products is several times faster so than by einsum),
        summed in einsum's order: Sₗₘ = (Aₗ₀Q₀₀Aₘ₀ + Aₗ₀Q₀₁Aₘ₁) + (Aₗ₁Q₁₀Aₘ₀ + Aₗ₁Q₁₁Aₘ₁).
        """
        A, Q, z = self.A[i], self.shape[j], self.centers[j]
        b = self.b[i]
        c = np.empty((len(i), 2))
        S = np.empty((len(i), 2, 2))
        for l in range(2):
            c[:, l] = A[:, l, 0] * z[:, 0] + A[:, l, 1] * z[:, 1] + b[:, l]
            for m in range(2):
                S[:, l, m] = (A[:, l, 0] * Q[:, 0, 0] * A[:, m, 0] + A[:, l, 0] * Q[:, 0, 1] * A[:, m, 1]) + (
                    A[:, l, 1] * Q[:, 1, 0] * A[:, m, 0] + A[:, l, 1] * Q[:, 1, 1] * A[:, m, 1])
        return c, S

    def point(self, owner: FloatArray, u: FloatArray) -> FloatArray:
        """World points A⁻¹(u − b) of unit-frame points u on ellipses `owner`."""
        return np.einsum("kij,kj->ki", self.Ainv[owner], u - self.b[owner])

    def angle(self, owner: FloatArray, z: FloatArray) -> FloatArray:
        u = np.einsum("kij,kj->ki", self.A[owner], z) + self.b[owner]
        return np.mod(np.arctan2(u[:, 1], u[:, 0]), 2.0 * np.pi)


def unit(theta: FloatArray) -> FloatArray:
    return np.stack([np.cos(theta), np.sin(theta)], axis=-1)
