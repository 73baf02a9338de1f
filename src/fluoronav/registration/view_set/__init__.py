"""One set of C-arm views registered: the bones, then the CM, in the CT frame (LPS, mm; §II-C).

:func:`register_view_set` is the chain the navigation (its first images and its verification after
the move) and the multi-view study share: ``pelvis`` (each view alone, the CM and its shaft left
out; each view's ``camera_from_ct`` follows, and a view that fails its checks is left out of every
later stage), ``femur`` (rotation about its head → ``ct_from_femur``, checked view by view) and
``cm`` (landmarks triangulated, roll scanned against the centrelines, the CM registered and checked
view by view). A later registration of the same anatomy differs in data (:class:`ViewSetPrior`: the kinematic
prediction, the earlier bones), not code; docs/navigation.md ("Stages") describes both. Modules: ``views``,
``settings``, ``bones`` (stages 1–2), ``cm`` (stage 3), ``fusion`` (tip from images and kinematics),
``unmoved`` (views of unmoved C-arm positions), ``register`` (the chain and its two halves).
"""

from typing import TYPE_CHECKING

from fluoronav.lazy import lazy_face

if TYPE_CHECKING:
    from fluoronav.registration.view_set.bones import ViewSetBones, register_view_set_bones
    from fluoronav.registration.view_set.cm import register_view_set_cm
    from fluoronav.registration.view_set.register import ViewSetRegistration, register_view_set
    from fluoronav.registration.view_set.settings import ViewSetPrior, ViewSetSeeds, ViewSetSettings
    from fluoronav.registration.view_set.views import FluoroView, ViewDetection, bone_views

__all__ = [
    "FluoroView",  # one C-arm image of a set: image, camera, the CM found in it
    "ViewDetection",  # the CM found in one view: landmarks, centreline, mask, confidence
    "ViewSetBones",  # the bones registered in a set: pelvis per view, cameras, femur, views left out
    "ViewSetPrior",  # what an earlier registration gives a later one (the verification after a move)
    "ViewSetRegistration",  # bones and CM registered in one set of views
    "ViewSetSeeds",  # the optimisers' seeds of the stages
    "ViewSetSettings",  # settings of a view-set registration (levels, checks, device)
    "bone_views",  # the views for the bone registrations, the CM and its shaft left out
    "register_view_set",  # bones, then CM, in one set of views
    "register_view_set_bones",  # the pelvis per view, then the femur (checked)
    "register_view_set_cm",  # the CM in a set whose cameras are known in one frame
]

__getattr__, __dir__ = lazy_face(__name__)
