"""Orthonormal bases: Laguerre and Kautz (Takenaka-Malmquist), continuous and discrete."""

from __future__ import annotations

from .kautz import KautzBasis, LaguerreBasis

__all__ = ["KautzBasis", "LaguerreBasis"]
