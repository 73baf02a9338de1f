"""The figures behind ``ViewSetSettings.min_unmoved_ncc``: how well two images of one C-arm position
agree (``fluoronav.registration.view_set.unmoved.unmoved_ncc``) when nothing moved and when the
patient moved a little.

For each seed: the demo's scene (ideal world, three 768² views, the CM at the working pose), its
images simulated twice with other quantum noise, then with the patient (pelvis and femur) moved by
0.5 mm, 1 mm, 2 mm and 0.5°. Prints one line per seed and motion with the three views' NCC.

Run::

    python tools/unmoved_ncc.py 3 11
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from fluoronav.geometry import se3
from fluoronav.registration.bone import BoneView
from fluoronav.registration.view_set.unmoved import unmoved_ncc
from fluoronav.simulation.navigation.scenario import SimulatedNavigationConfig, build_scenario
from fluoronav.simulation.world import IDEAL, MotionWorld

#: (label, the patient's motion moved_from_world) of each comparison
MOTIONS = (
    ("nothing moved", np.eye(4)),
    ("0.5 mm", se3.make(np.eye(3), (0.5, 0.0, 0.0))),
    ("1 mm", se3.make(np.eye(3), (0.0, 0.7, 0.7))),
    ("2 mm", se3.make(np.eye(3), (2.0, 0.0, 0.0))),
    ("0.5°", se3.make(Rotation.from_rotvec(np.radians([0.0, 0.5, 0.0])).as_matrix(), (0.0, 0.0, 0.0))),
)


def _bone_view(im: Any) -> BoneView:
    """The image with its CM left out."""
    return BoneView(np.asarray(im.image, np.float32), im.camera, np.logical_not(im.mask))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("seeds", type=int, nargs="+")
    args = parser.parse_args()
    # the patient may move (by nothing unless asked): the ideal world otherwise
    world = dataclasses.replace(IDEAL, motion=MotionWorld(between_sets_mm=1e-9))
    for seed in args.seeds:
        cfg = SimulatedNavigationConfig(seed=seed, world=world)
        s = build_scenario(
            cfg, "phantom", lambda name: contextlib.nullcontext(), np.random.default_rng(seed), seed, seed + 1
        )
        before = [_bone_view(im) for im in s.simulate(s.W_regi, s.cams, 100)]
        for label, moved in MOTIONS:
            after = [_bone_view(im) for im in s.simulate(s.W_regi, s.cams, 200, moved_from_world=moved)]
            ncc = [unmoved_ncc(b, a) for b, a in zip(before, after, strict=True)]
            print(f"seed {seed}, {label}: " + ", ".join(f"{x:.4f}" for x in ncc))


if __name__ == "__main__":
    main()
