"""fluoronav: fluoroscopic navigation of a surgical robot carrying a continuum manipulator (CM).

Pipeline stages live in sub-packages: ``geometry`` (frames, cameras), ``manipulator`` (CM model),
``anatomy`` (CT, phantom), ``rendering`` (DRRs), ``simulation`` (physics X-ray), ``detection``
(learned CM detector), ``registration`` (2D/3D), ``calibration`` (hand-eye), ``navigation``,
``studies`` and ``cli``.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("fluoronav")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
