"""Obstacle ellipses: Löwner–John fits (eq. 1), tight covers, and gaps between ellipses (eq. 3)."""

from services.ellipsoids.mvee import FitError, mvee, mvee_fast

__all__ = ["FitError", "mvee", "mvee_fast"]
