"""The learned CM detector: landmarks A and B, the mask and the centreline of the CM in an X-ray image.

A model declares its stages (``config``); :class:`~fluoronav.detection.detector.Detector` runs them
(``detector``; its result and output files in ``result``, image files in ``image_io``). The parts:
``model`` and ``runtime`` (the networks and their inference copies), ``views`` and ``patches`` (the
samplers), ``heatmaps`` and ``decoder`` (from outputs to landmarks and a mask), ``localize`` (coarse
and fine), ``patch_stages`` (refinement, tube mask, mask ends), ``checks`` and ``evidence`` (the
free-end, shaft and edge checks). ``centerline``, ``instrument`` and ``tube_profile`` work from a
detection; ``training`` (data sets, augmentation, losses, training, evaluation) is not loaded by
``navigate``. The model card: docs/detector.md.
"""

from typing import TYPE_CHECKING

from fluoronav.lazy import lazy_face

if TYPE_CHECKING:
    from fluoronav.detection.centerline import extract_centerline, resample_polyline
    from fluoronav.detection.config import DetectorConfig
    from fluoronav.detection.detector import Detector, load_image, shipped_model_path
    from fluoronav.detection.instrument import instrument_mask, instrument_masks
    from fluoronav.detection.result import Detection, detection_to_dict, write_detection

__all__ = [
    "Detection",  # one image's result: landmarks A and B, confidences, mask, centreline, why not
    "Detector",  # the learned CM detector (the shipped model by default), CPU or CUDA
    "DetectorConfig",  # a model's declared stages and their settings
    "detection_to_dict",  # a detection as a JSON-ready dict (the detect command's output)
    "extract_centerline",  # the CM's 2D centreline from its mask and landmarks
    "instrument_mask",  # the CM and its mounting shaft in one image, to leave out of bone similarity
    "instrument_masks",  # the instrument masks of several views
    "load_image",  # an X-ray image file (npy, png, tiff, DICOM) as a log image and its pixel spacing
    "resample_polyline",  # a polyline resampled by arc length
    "shipped_model_path",  # the path of the detector model shipped with fluoronav
    "write_detection",  # writes a detection's JSON, mask and overlay
]

__getattr__, __dir__ = lazy_face(__name__)
