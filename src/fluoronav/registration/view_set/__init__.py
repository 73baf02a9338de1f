"""One set of C-arm views registered: the bones, then the CM, in the CT frame (§II-C).

The chain that the navigation (its first images and its verification after the move) and the
multi-view study share, :func:`register_view_set`, in three stages:

1. ``pelvis``: the pelvis registered to each view alone, with the CM and its shaft left out of the
   similarity (:func:`bone_views`); each view's ``camera_from_ct`` follows, and with it the views'
   relative geometry. After a move (:class:`ViewSetPrior`), each view's pelvis again with the
   femur's footprint (the femur where the earlier registration put it) left out as well. Each
   view's pelvis is checked (:mod:`fluoronav.registration.bone.checks`); a view that fails (a
   mirrored image, a wrong camera) is left out of every later stage.
2. ``femur``: the femur (rotation about its head) registered to the views in the CT frame →
   ``ct_from_femur``, checked view by view; a view that fails is left out and the femur
   registered again without it.
3. ``cm``: the CM's landmarks triangulated over the views and its roll scanned against the
   centrelines (:func:`~fluoronav.registration.centerline.centerline_initialize_multiview`), then
   the CM registered (pose and shape) from the best roll minima and checked view by view
   (:mod:`fluoronav.registration.cm.checks`). After a move the CM is registered from the robot's
   kinematic prediction where the views' checks pass it, else from the images' own starts screened
   together with the prediction (the plan's pose the fallback); the result is compared with the
   prediction (reported, not judged) and, where consistent, its tip fused with the predicted one,
   each weighted by its uncertainty (``fusion``).

Where the views' cameras are already close (taken from registered views' C-arm positions moved by
the C-arm's known motion: :attr:`ViewSetSettings.local`) the bones need only their local levels;
where the C-arm did not move and the anatomy did not either (``unmoved``), the earlier bones are
kept (``known_bones``).

:func:`register_view_set_bones` and :func:`register_view_set_cm` are the two halves, for workflows
that keep their own CM registration or know their cameras. What differs in a later registration of
the same anatomy is data (:class:`ViewSetPrior`), not code. Each stage is timed and its diagnostics
recorded through a :data:`~fluoronav.registration.stages.StageRecorder`.

Modules: ``views`` (:class:`FluoroView`, :class:`ViewDetection`, :func:`bone_views`), ``settings``
(:class:`ViewSetSettings`, :class:`ViewSetSeeds`, :class:`ViewSetPrior`), ``bones`` (stages 1–2),
``cm`` (stage 3), ``fusion`` (the tip from the images and the kinematics), ``unmoved`` (views of
unmoved C-arm positions), ``register`` (the chain, :class:`ViewSetRegistration`).

Frames: ``ct`` (LPS, mm) is the world frame of the registered views; ``femur`` is the CT frame
moved with the femur (``ct_from_femur``).
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

__getattr__, __dir__ = lazy_face(
    __name__,
    {
        "fluoronav.registration.view_set.bones": ("ViewSetBones", "register_view_set_bones"),
        "fluoronav.registration.view_set.cm": ("register_view_set_cm",),
        "fluoronav.registration.view_set.register": ("ViewSetRegistration", "register_view_set"),
        "fluoronav.registration.view_set.settings": ("ViewSetPrior", "ViewSetSeeds", "ViewSetSettings"),
        "fluoronav.registration.view_set.views": ("FluoroView", "ViewDetection", "bone_views"),
    },
)
