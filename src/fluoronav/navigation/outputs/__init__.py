"""What the navigation writes and sends: navigation.json, the HTML report, 3D Slicer files, OpenIGTLink.

``files``: ``navigation.json`` and the output folder; ``report``: ``report.html``; ``slicer``: a
folder 3D Slicer loads; ``igtl``: the live OpenIGTLink stream.
"""

from typing import TYPE_CHECKING

from fluoronav.lazy import lazy_face

if TYPE_CHECKING:
    from fluoronav.navigation.outputs.files import write_navigation_json, write_outputs
    from fluoronav.navigation.outputs.igtl import IGTLinkStreamer
    from fluoronav.navigation.outputs.report import write_report
    from fluoronav.navigation.outputs.slicer import write_slicer_folder

__all__ = [
    "IGTLinkStreamer",  # streams images, transforms and status to 3D Slicer's OpenIGTLink server
    "write_navigation_json",  # navigation.json alone, written whole at once
    "write_outputs",  # navigation.json, slicer/ and report.html of a result
    "write_report",  # the self-contained HTML report
    "write_slicer_folder",  # the registered CM and femur, plan and landmarks as Slicer files
]

__getattr__, __dir__ = lazy_face(__name__)
