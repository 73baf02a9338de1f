"""The navigation loop on a simulated patient and robot: the demo, ``study navigation`` and its faults.

A simulation harness above the product: it builds a scenario (patient, robot, C-arm views), writes
it as a user's case, runs :mod:`fluoronav.navigation` on it, moves the simulated robot and measures
the result against the truth. ``fluoronav navigate`` never loads it.
"""

from typing import TYPE_CHECKING

from fluoronav.lazy import lazy_face

if TYPE_CHECKING:
    from fluoronav.simulation.navigation.demo import run_demo, write_demo_outputs
    from fluoronav.simulation.navigation.faults import get_fault
    from fluoronav.simulation.navigation.loop import SimulatedNavigationConfig, run_simulated_navigation

__all__ = [
    "SimulatedNavigationConfig",  # the simulated world of the demo and study navigation
    "get_fault",  # an input fault of the fault study by name
    "run_demo",  # the demo: a simulated case written to files, then navigated
    "run_simulated_navigation",  # the loop on a simulated patient and robot, with the truth
    "write_demo_outputs",  # the demo's results.json, navigation.json, slicer/ and report
]

__getattr__, __dir__ = lazy_face(__name__)
