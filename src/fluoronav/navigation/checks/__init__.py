"""The checks around the registrations: the preflight of a case's inputs and plan, and safety.

``preflight``: inputs and plan before any registration (``preflight_images``: the images and
cameras; ``preflight_config``: thresholds and findings); ``safety``: the thresholds a registration
must pass and the bounds of the robot's commands.
"""

from typing import TYPE_CHECKING

from fluoronav.lazy import lazy_face

if TYPE_CHECKING:
    from fluoronav.navigation.checks.preflight import PreflightFinding, PreflightInputError, preflight
    from fluoronav.navigation.checks.preflight_config import PreflightConfig
    from fluoronav.navigation.checks.safety import SafetyConfig

__all__ = [
    "PreflightConfig",  # thresholds of the checks that run before any registration
    "PreflightFinding",  # one preflight problem: input (exit 2) or plan (refusal, exit 3)
    "PreflightInputError",  # the preflight's input error, naming its first finding's check
    "SafetyConfig",  # thresholds a registration must pass before the robot may act on it
    "preflight",  # every input and plan check of a case, before registration
]

__getattr__, __dir__ = lazy_face(__name__)
