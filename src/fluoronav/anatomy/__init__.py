"""Anatomy: CT volumes, labels, landmarks and the built-in procedural hip phantom.

- :mod:`~fluoronav.anatomy.volume`: :class:`Volume`, a scalar volume in its physical frame (LPS,
  mm) with optional labels and landmarks, and the HU → μ conversion;
- :mod:`~fluoronav.anatomy.io`: CTs with their label maps and landmarks from NIfTI, NRRD, MetaImage
  and DICOM series, and back;
- :mod:`~fluoronav.anatomy.landmarks`, :mod:`~fluoronav.anatomy.markups`: landmark files (3D Slicer
  FCSV and ``.mrk.json`` markups, a small JSON format);
- :mod:`~fluoronav.anatomy.phantom`: the seeded hip phantom (pelvis and both proximal femurs, HU)
  that the demo, the studies and the tests use.
"""

from typing import TYPE_CHECKING

from fluoronav.lazy import lazy_face

if TYPE_CHECKING:
    from fluoronav.anatomy.io import VOLUME_SUFFIXES, load_ct, load_label_map, resolve_ct, save_volume
    from fluoronav.anatomy.landmarks import (
        read_fcsv,
        read_landmarks,
        read_landmarks_json,
        write_fcsv,
        write_landmarks,
        write_landmarks_json,
    )
    from fluoronav.anatomy.markups import MarkupNode, read_markup_nodes, read_markups, write_markups
    from fluoronav.anatomy.phantom import LABEL_NAMES, hip_phantom
    from fluoronav.anatomy.volume import MU_WATER_PER_MM, Volume, hu_to_mu

__all__ = [
    "LABEL_NAMES",  # the phantom's labels: {1: "pelvis", 2: "femur_left", 3: "femur_right"}
    "MU_WATER_PER_MM",  # default linear attenuation of water, 1/mm (HU → μ)
    "VOLUME_SUFFIXES",  # file suffixes read as volumes (.nii.gz, .nii, .nrrd, .nhdr, .mha, .mhd)
    "MarkupNode",  # one markup of a Slicer .mrk.json file with its control points in LPS mm
    "Volume",  # scalar volume (nz, ny, nx) in its physical frame (LPS, mm), labels, landmarks
    "hip_phantom",  # the seeded procedural hip phantom in HU, with labels and landmarks
    "hu_to_mu",  # HU → linear attenuation μ in 1/mm
    "load_ct",  # a CT (NIfTI, NRRD, MHA, DICOM directory) with its sibling labels and landmarks
    "load_label_map",  # an integer label map, checked against a volume's grid
    "read_fcsv",  # landmarks of a Slicer FCSV file → name → LPS point mm
    "read_landmarks",  # landmarks of a file by suffix (.mrk.json, .fcsv, .json)
    "read_landmarks_json",  # landmarks of fluoronav's small JSON format
    "read_markup_nodes",  # every markup of a Slicer .mrk.json file
    "read_markups",  # every placed control point of a .mrk.json file → label → LPS point mm
    "resolve_ct",  # "phantom" → hip_phantom(seed), else load_ct(path)
    "save_volume",  # write a volume and its labels, label names and landmarks
    "write_fcsv",  # write landmarks as a Slicer FCSV file
    "write_landmarks",  # write landmarks by suffix (.mrk.json, .fcsv, .json)
    "write_landmarks_json",  # write landmarks in fluoronav's JSON format
    "write_markups",  # write one markup (point list, line or curve) as a Slicer .mrk.json file
]

__getattr__, __dir__ = lazy_face(__name__)
