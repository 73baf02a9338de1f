"""From registered poses to a robot command: the navigation loop of Gao et al. (2022), III-D.

- :mod:`~fluoronav.navigation.case`: a navigation case (CT, plan, CM, robot, C-arm views) and its
  file; :mod:`~fluoronav.navigation.planning`: plans;
- :mod:`~fluoronav.navigation.preflight`: the case's inputs and plan checked before any registration;
- :mod:`~fluoronav.navigation.pipeline`: detection, registration of each set of views, the robot
  command, verification and correction (``fluoronav navigate``);
- :mod:`~fluoronav.navigation.targeting`: eqs. 7–8, the robot target and the tip correction;
- :mod:`~fluoronav.navigation.safety`: the thresholds a registration must pass before the robot acts;
- :mod:`~fluoronav.navigation.outputs`, :mod:`~fluoronav.navigation.report`,
  :mod:`~fluoronav.navigation.slicer`, :mod:`~fluoronav.navigation.igtl`: navigation.json, the HTML
  report, 3D Slicer files and the OpenIGTLink stream;
- :mod:`~fluoronav.navigation.simulated`, :mod:`~fluoronav.navigation.demo`: the loop on simulated
  cases with a simulated robot (the demo and ``study navigation``).
"""

from fluoronav.navigation.case import CaseView, NavigationCase, VerificationViews, load_navigation_case
from fluoronav.navigation.pipeline import (
    NavigationConfig,
    NavigationRefused,
    NavigationResult,
    navigate,
    verify,
)
from fluoronav.navigation.planning import Plan, load_plan, planned_femur_from_cm
from fluoronav.navigation.preflight import PreflightConfig, PreflightFinding, preflight
from fluoronav.navigation.safety import SafetyConfig
from fluoronav.navigation.simulated import SimulatedNavigationConfig, run_simulated_navigation
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
    "SimulatedNavigationConfig",  # the simulated world of the demo and study navigation
    "UnreachableTarget",  # the robot cannot reach the pose the plan needs
    "VerificationViews",  # the images after the move and the joints read with them
    "load_navigation_case",  # reads and validates a navigation case file
    "load_plan",  # reads a plan (JSON or Slicer markups)
    "navigate",  # the whole pipeline on a case: detection to robot command (and verification)
    "planned_femur_from_cm",  # the CM base pose in the femur frame that realises a plan
    "preflight",  # every input and plan check of a case, before registration
    "robot_target",  # eqs. 7–8 and inverse kinematics: the joint target for a planned CM pose
    "run_simulated_navigation",  # the loop on a simulated patient and robot, with the truth
    "tip_correction_target",  # the corrective move that slides the registered CM's tip onto the plan
    "verify",  # registers the verification views and commands one correction
]
