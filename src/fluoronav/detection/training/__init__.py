"""Training the CM detector: simulated data sets, augmentation, losses, the training loop, evaluation.

Not loaded by ``fluoronav navigate``; the detector itself is :mod:`fluoronav.detection`.
"""

from typing import TYPE_CHECKING

from fluoronav.lazy import lazy_face

if TYPE_CHECKING:
    from fluoronav.detection.training.config import TrainConfig
    from fluoronav.detection.training.train import train

__all__ = [
    "TrainConfig",  # settings of a training run (data, stages, schedule, seed)
    "train",  # trains (or resumes) a detector model on simulated data sets
]

__getattr__, __dir__ = lazy_face(__name__)
