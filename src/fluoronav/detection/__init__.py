"""The learned CM detector: landmarks A and B, the mask and the centreline of the CM in an X-ray image.

A model declares its stages (:mod:`~fluoronav.detection.config`); :class:`~fluoronav.detection.
detector.Detector` runs them. Modules:

- ``config``: the declared configuration (stages and their settings); ``flat_config``: the flat
  configuration of model files of format 1 mapped onto it.
- ``model``: the networks and the model files; ``runtime``: the networks on a device for inference.
- ``views``: the view sampler (coarse, fine); ``patches``: the tube-aligned patch sampler.
- ``heatmaps``: heatmap targets and peak decoding; ``decoder``: the rules that turn the stages'
  outputs into landmarks and a mask.
- ``localize``: the coarse and fine stages; ``patch_stages``: refinement, tube mask, mask ends;
  ``checks``: the free-end, shaft and edge checks; ``evidence``: the image measures they use.
- ``detector``: the :class:`~fluoronav.detection.detector.Detector`; ``result``: its
  :class:`~fluoronav.detection.result.Detection` and output files; ``image_io``: image files.
- ``centerline``, ``instrument``, ``tube_profile``: the centreline, the instrument masks and the
  tube's intensity profile, from a detection.
- ``dataset``, ``augment``, ``training_patches``, ``loss``, ``train``: training; ``evaluate``,
  ``bench``: accuracy and speed.
"""
