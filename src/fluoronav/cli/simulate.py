"""``fluoronav simulate``: realistic X-ray samples of the CM over anatomy."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import typer

from fluoronav.cli.common import DEVICE_OPTION, SEED_OPTION

if TYPE_CHECKING:
    from fluoronav.simulation.sample_variation import SampleVariation

_MAX_PROJECTED_AB_OPTION = typer.Option(
    None,
    "--max-projected-ab-mm",
    min=0.1,
    help="Keep only foreshortened views: landmarks A and B at most this far apart on the "
    "detector (mm; a CM across the view projects ~60 mm). For training sets rich in hard views.",
)

_MAX_SHAFT_OPTION = typer.Option(
    None,
    "--max-shaft-mm",
    min=0.1,
    help="Keep only views whose mounting shaft projects at most this long on the detector "
    "(mm; the 50 mm shaft across the view projects ~110 mm): the shaft seen nearly along its "
    "axis, a short stub at the CM's base. For training sets rich in hard views.",
)

_MAX_SHAFT_ANGLE_OPTION = typer.Option(
    None,
    "--max-shaft-angle-deg",
    min=0.1,
    max=180.0,
    help="Keep only views where the CM's chord A-B and its mounting shaft meet at A at most "
    "this angle on the detector (degrees; ~180 where the shaft goes on behind the CM, 20-70 a "
    "V, under 35 the CM over its shaft). For training sets rich in hard views.",
)

_SHAFT_LENGTH_OPTION = typer.Option(
    50.0,
    "--shaft-length-mm",
    min=0.0,
    help="Length of the rigid tube the CM is mounted on (0: the bare CM). The default tube "
    "ends in the field; a robot's shaft that leaves the field is ~200 mm or more.",
)

_WORLD_OPTION = typer.Option(
    "ideal",
    "--world",
    help="The simulated world's error sources: ideal, realistic, or a JSON file of magnitudes "
    "(docs/simulation.md). Its patient, the CM as built and the C-arm's flex reach the images; "
    "the labels are the true ones.",
)

_SCENES_OPTION = typer.Option(
    "paper",
    "--scenes",
    help="paper: the paper's random views; navigation: the navigation's own views (the CM at the "
    "working pose, approaching the femur along the plan, inserted); mixed: each sample one or the other.",
)

_NAVIGATION_FRACTION_OPTION = typer.Option(
    0.5,
    "--navigation-fraction",
    min=0.0,
    max=1.0,
    help="With --scenes mixed: the share of navigation scenes.",
)


_RANDOMISE_OPTION = typer.Option(
    "off",
    "--randomise",
    help="Domain randomisation per sample: off, or realistic (spectrum, dose, blur, scatter, "
    "collimation, wedge, detector response, partial field of view, rotation and transpose; "
    "docs/simulation.md). Each draw is recorded in the manifest row.",
)

_DISTRACTORS_OPTION = typer.Option(
    "off",
    "--distractors",
    help="Distractor metal (K-wires, screws, a second tube, cables) near the CM: off or realistic.",
)

_DISTRACTOR_FRACTION_OPTION = typer.Option(
    0.5,
    "--distractor-fraction",
    min=0.0,
    max=1.0,
    help="With --distractors: the share of samples that get distractor metal.",
)


def _variation(randomise: str, distractors: str, fraction: float) -> SampleVariation:
    """The data set's :class:`SampleVariation` from the presets' names (a one-line error for another)."""
    from fluoronav.simulation.distractors import DISTRACTOR_PRESETS
    from fluoronav.simulation.randomisation import RANDOMISATION_PRESETS
    from fluoronav.simulation.sample_variation import SampleVariation

    for name, presets, option in (
        (randomise, RANDOMISATION_PRESETS, "--randomise"),
        (distractors, DISTRACTOR_PRESETS, "--distractors"),
    ):
        if name not in presets:
            raise typer.BadParameter(f"{name!r}; use one of {', '.join(presets)}", param_hint=option)
    return SampleVariation(
        randomisation=RANDOMISATION_PRESETS[randomise],
        distractors=DISTRACTOR_PRESETS[distractors],
        p_distractors=fraction,
    )


def register(app: typer.Typer) -> None:
    @app.command("simulate")
    def simulate(
        n: int = typer.Option(..., "--n", min=1, help="Number of samples in the data set."),
        out: Path = typer.Option(..., "--out", help="Output directory (rerun to resume)."),
        ct: list[str] = typer.Option(
            ["phantom"], "--ct", help="CT file/DICOM dir, or 'phantom' (repeatable)."
        ),
        seed: int = SEED_OPTION,
        scheduler: str = typer.Option(None, "--scheduler", help="Address of an existing Dask scheduler."),
        workers: int = typer.Option(
            None, "--workers", min=0, help="Local worker processes (default: up to 2; 0 = in this process)."
        ),
        no_cm: bool = typer.Option(False, "--no-cm", help="Make the same kind of images without a CM."),
        size: int = typer.Option(
            512, "--size", min=32, help="Stored image size in pixels (the 1536² detector is binned to it)."
        ),
        phantoms: int = typer.Option(
            4, "--phantoms", min=1, help="Phantom anatomies (seeds) to cycle through."
        ),
        max_projected_ab_mm: float = _MAX_PROJECTED_AB_OPTION,
        max_projected_shaft_mm: float = _MAX_SHAFT_OPTION,
        max_shaft_angle_deg: float = _MAX_SHAFT_ANGLE_OPTION,
        shaft_length_mm: float = _SHAFT_LENGTH_OPTION,
        world: str = _WORLD_OPTION,
        scenes: str = _SCENES_OPTION,
        navigation_fraction: float = _NAVIGATION_FRACTION_OPTION,
        randomise: str = _RANDOMISE_OPTION,
        distractors: str = _DISTRACTORS_OPTION,
        distractor_fraction: float = _DISTRACTOR_FRACTION_OPTION,
        device: str = DEVICE_OPTION,
    ) -> None:
        """Simulate a data set of X-ray images with labels (manifest.jsonl + samples/*.npz).

        Scenes follow the paper's sampling (control points U[-7.9, 7.9] deg, source-to-isocentre
        400-500 mm, LAO/RAO 0-360 deg, CRAN/CAUD 75-105 deg, +-20 mm translation), the CM in and
        around a femur (or the bone nearest the centre of an unlabelled CT). Images are stored at
        --size (the 1536 px detector binned; landmarks, camera and pixel spacing in the manifest
        refer to the stored pixels). --scenes navigation draws the navigation's own views instead,
        --world the world they are imaged in, --randomise and --distractors what each sample varies
        beyond it. Samples are written as they finish; rerun to resume.
        The same --seed gives the same samples for any number of workers.
        """
        from fluoronav.device import resolve_device  # heavy: torch
        from fluoronav.simulation.dataset import DatasetSpec, simulate_dataset  # lazy: fast --help
        from fluoronav.simulation.world import load_world  # lazy: fast --help

        simulated_world = load_world(world)  # an unknown world or a bad file is bad input
        variation = _variation(randomise, distractors, distractor_fraction)

        try:
            spec = DatasetSpec(
                cts=tuple(ct),
                n_phantoms=phantoms,
                with_cm=not no_cm,
                image_size=size,
                seed=seed,
                device=str(resolve_device(device)),
                max_projected_ab_mm=max_projected_ab_mm,
                shaft_length_mm=shaft_length_mm,
                max_projected_shaft_mm=max_projected_shaft_mm,
                max_shaft_angle_deg=max_shaft_angle_deg,
                world=simulated_world,
                scenes=scenes,
                navigation_fraction=navigation_fraction,
                variation=variation,
            )
        except ValueError as exc:  # settings that contradict each other
            raise typer.BadParameter(str(exc)) from exc
        rows = simulate_dataset(out, n, spec, scheduler=scheduler, workers=workers)
        typer.echo(f"{len(rows)} new samples; data set in {out}/ (manifest.jsonl, contact_sheet.png)")
