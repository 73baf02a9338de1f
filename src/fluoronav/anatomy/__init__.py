"""Anatomy: CT volumes, labels, landmarks and the built-in procedural hip phantom."""

from fluoronav.anatomy.volume import MU_WATER_PER_MM, Volume, hu_to_mu

__all__ = ["MU_WATER_PER_MM", "Volume", "hu_to_mu"]
