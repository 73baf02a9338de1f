"""A navigation case: the CT, plan, CM, robot state, hand-eye matrix and C-arm views, and its files.

``model``: the case in memory and its ``navigation.json``; ``schema``: the file's keys and types as
pydantic models; ``parse``: the files it names, read and checked; ``view``: one C-arm image of a case.
"""

from typing import TYPE_CHECKING

from fluoronav.lazy import lazy_face

if TYPE_CHECKING:
    from fluoronav.navigation.case.model import (
        NavigationCase,
        VerificationViews,
        load_navigation_case,
        write_navigation_case,
    )
    from fluoronav.navigation.case.view import CaseView

__all__ = [
    "CaseView",  # one C-arm image of a case: image, camera, optional landmarks and mask
    "NavigationCase",  # everything navigate needs: CT, plan, CM, robot state, hand-eye, views
    "VerificationViews",  # the images after the move and the joints read with them
    "load_navigation_case",  # reads and validates a navigation case file
    "write_navigation_case",  # writes a case as files navigate reads back
]

__getattr__, __dir__ = lazy_face(__name__)
