"""Optimisation settings of the detector's training (:class:`TrainConfig`) and the rules on them."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["TrainConfig"]


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings.

    Attributes:
        epochs: number of epochs (total, also when resuming).
        batch_size: samples per step.
        lr: initial Adam learning rate.
        lr_step_epochs, lr_gamma: lr × lr_gamma every lr_step_epochs epochs.
        heatmap_weight: weight of the heatmap L2 term
            (:func:`~fluoronav.detection.training.loss.detector_loss`).
        heatmap_fg_weight: extra per-pixel weight of the L2 term where the target is high.
        bce_weight: weight of a binary cross-entropy term added to the Dice loss (0: Dice only, as in
            the paper; Dice alone converges slowly from random weights).
        val_fraction: fraction of sample ids held out for validation.
        seed: seed of the weights, the shuffling and the augmentations.
        device: ``cpu``, ``cuda`` or ``auto``.
        workers: data loader worker processes.
        max_steps_per_epoch: stop each epoch after this many steps (None: the whole split).
        augment: augment the training samples.
        stages: the stages trained (``("coarse", "fine")``, or one of them): the others keep their
            weights and are not run, so fine-tuning only the fine stage costs about half a step.
            ``("refine",)`` trains the landmark refinement stage alone on tube-aligned patches
            (:class:`~fluoronav.detection.training.dataset.RefineDataset`), adding it to a model without
            one; ``("ends",)`` the mask-end stage alone
            (:class:`~fluoronav.detection.training.dataset.EndsDataset`,
            BCE + Dice on the patch masks), likewise; ``("tube",)`` the tube-mask stage alone, likewise;
            ``("shaft",)`` the shaft stage alone (tube-mask patches, some on the mounting shaft:
            ``tube_shaft_prob``), added to a model without one with the tube-mask stage's weights.
        edge_negative_prob: probability that a CM-free sample's fine ROI is centred on a strong edge
            of its image (``AugmentConfig.p_edge_negative_roi``) rather than anywhere.
        refine_repeats: patches per landmark and sample in an epoch of the refinement or the mask-end
            stage.
        collimate_prob: probability that a training sample is cropped to a collimated field of view
            first (:func:`~fluoronav.detection.training.augment.collimation_window`, ``p_collimate``).
        partial_roi_prob: probability that a training sample's fine ROI is fitted to a part of its
            CM only (``AugmentConfig.p_partial_roi``).
        tube_shaft_prob: with ``("tube",)`` or ``("shaft",)``, probability that a patch is centred
            on the projected mounting shaft instead of the CM's centreline (where the manifest has
            the camera and the pose; :func:`~fluoronav.detection.ends.training_tube_patch`).
    """

    epochs: int = 10
    batch_size: int = 16
    lr: float = 1e-3
    lr_step_epochs: int = 10
    lr_gamma: float = 0.1
    heatmap_weight: float = 1.0
    heatmap_fg_weight: float = 20.0
    bce_weight: float = 1.0
    val_fraction: float = 1 / 11
    seed: int = 0
    device: str = "auto"
    workers: int = 0
    max_steps_per_epoch: int | None = None
    augment: bool = True
    stages: tuple[str, ...] = ("coarse", "fine")
    collimate_prob: float = 0.0
    partial_roi_prob: float = 0.0
    edge_negative_prob: float = 0.0
    refine_repeats: int = 5
    tube_shaft_prob: float = 0.0

    def __post_init__(self) -> None:
        alone = self.stages in (("refine",), ("ends",), ("tube",), ("shaft",))
        if not alone and (not self.stages or not set(self.stages) <= {"coarse", "fine"}):
            raise ValueError(
                "stages must be 'coarse' and/or 'fine', or one of 'refine', 'ends', 'tube', 'shaft' alone, "
                f"got {self.stages}"
            )
        if self.refine_repeats < 1:
            raise ValueError(f"refine_repeats must be 1 or more, got {self.refine_repeats}")
        if not 0.0 <= self.collimate_prob <= 1.0:
            raise ValueError(f"collimate_prob must be in [0, 1], got {self.collimate_prob}")
        if not 0.0 <= self.partial_roi_prob <= 1.0:
            raise ValueError(f"partial_roi_prob must be in [0, 1], got {self.partial_roi_prob}")
        if not 0.0 <= self.edge_negative_prob <= 1.0:
            raise ValueError(f"edge_negative_prob must be in [0, 1], got {self.edge_negative_prob}")
        if not 0.0 <= self.tube_shaft_prob <= 1.0:
            raise ValueError(f"tube_shaft_prob must be in [0, 1], got {self.tube_shaft_prob}")
        if self.tube_shaft_prob > 0.0 and self.stages not in (("tube",), ("shaft",)):
            raise ValueError("tube_shaft_prob applies to the stages 'tube' and 'shaft' (trained alone)")
        if self.stages == ("shaft",) and self.tube_shaft_prob <= 0.0:
            raise ValueError("the shaft stage learns from patches on the shaft: give tube_shaft_prob > 0")
