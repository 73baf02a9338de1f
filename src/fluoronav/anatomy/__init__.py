"""Anatomy: CT volumes, labels, landmarks and the built-in procedural hip phantom."""

from fluoronav.anatomy.io import load_ct, load_label_map, resolve_ct, save_volume
from fluoronav.anatomy.landmarks import (
    read_fcsv,
    read_landmarks,
    read_landmarks_json,
    write_fcsv,
    write_landmarks,
    write_landmarks_json,
)
from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.anatomy.volume import MU_WATER_PER_MM, Volume, hu_to_mu

__all__ = [
    "MU_WATER_PER_MM",
    "Volume",
    "hip_phantom",
    "hu_to_mu",
    "load_ct",
    "load_label_map",
    "read_fcsv",
    "read_landmarks",
    "read_landmarks_json",
    "resolve_ct",
    "save_volume",
    "write_fcsv",
    "write_landmarks",
    "write_landmarks_json",
]
