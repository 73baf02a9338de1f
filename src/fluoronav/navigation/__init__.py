"""From registered poses to a robot command: the navigation loop of Gao et al. (2022), III-D.

- ``case``: a navigation case (CT, plan, CM, robot, C-arm views), its schema and files;
  ``planning``: plans; ``targeting``: eqs. 7–8, the robot target and the tip correction;
- ``pipeline``: detection, registration of each set of views, the robot command, verification and
  correction (``fluoronav navigate``); ``config``: its settings tree;
- ``checks``: the preflight of the inputs and plan, and the safety thresholds;
- ``outputs``: navigation.json, the HTML report, 3D Slicer files and the OpenIGTLink stream.

The simulated loop (demo, ``study navigation``) is :mod:`fluoronav.simulation.navigation`.
"""

from typing import TYPE_CHECKING

from fluoronav.lazy import lazy_face

if TYPE_CHECKING:
    from fluoronav.navigation.case.model import (
        CaseView,
        NavigationCase,
        VerificationViews,
        load_navigation_case,
    )
    from fluoronav.navigation.checks.preflight import PreflightConfig, PreflightFinding, preflight
    from fluoronav.navigation.checks.safety import SafetyConfig
    from fluoronav.navigation.pipeline import (
        NavigationConfig,
        NavigationRefused,
        NavigationResult,
        navigate,
        verify,
    )
    from fluoronav.navigation.planning import Plan, load_plan, planned_femur_from_cm
    from fluoronav.navigation.targeting import UnreachableTarget, robot_target, tip_correction_target

__all__ = [
    "CaseView",  # one C-arm image of a case: image, camera, optional landmarks and mask
    "NavigationCase",  # everything navigate needs: CT, plan, CM, robot state, hand-eye, views
    "NavigationConfig",  # the pipeline's settings: stages' registrations, checks, device, seed
    "NavigationRefused",  # a stage refused: stage, check, view and reason; no robot command
    "NavigationResult",  # stages, registrations, commands, status and reason (navigation.json)
    "Plan",  # a planned CM target: entry, direction, depth, optional roll and shape
    "PreflightConfig",  # thresholds of the checks that run before any registration
    "PreflightFinding",  # one preflight problem: input (exit 2) or plan (refusal, exit 3)
    "SafetyConfig",  # thresholds a registration must pass before the robot may act on it
    "UnreachableTarget",  # the robot cannot reach the pose the plan needs
    "VerificationViews",  # the images after the move and the joints read with them
    "load_navigation_case",  # reads and validates a navigation case file
    "load_plan",  # reads a plan (JSON or Slicer markups)
    "navigate",  # the whole pipeline on a case: detection to robot command (and verification)
    "planned_femur_from_cm",  # the CM base pose in the femur frame that realises a plan
    "preflight",  # every input and plan check of a case, before registration
    "robot_target",  # eqs. 7–8 and inverse kinematics: the joint target for a planned CM pose
    "tip_correction_target",  # the corrective move that slides the registered CM's tip onto the plan
    "verify",  # registers the verification views and commands one correction
]

__getattr__, __dir__ = lazy_face(__name__)
