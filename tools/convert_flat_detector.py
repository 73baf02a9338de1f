"""Convert a detector model file of format 1 (one flat dictionary of settings) to format 2 (the declared
stages of :class:`fluoronav.detection.config.DetectorConfig`), which is the only format fluoronav reads.

A flat configuration maps onto the declared stages: a missing key takes its default of
:data:`FLAT_DEFAULTS` (a file without ``heatmap`` predates the softmax heatmaps: ``"gaussian"``); a
stage is listed where its settings switch it on (a network stage where it has channels, a check
where its threshold is above 0); a network whose check is off (``shaft_channels`` with
``shaft_cut_min_mm`` 0) is not listed. Keys of stages that fluoronav no longer has (:data:`RETIRED`)
and the weights of networks not listed are left out. The weights of the listed networks are copied
unchanged; the other entries (version, normalisation, training record, metrics) are kept, and the
JSON sidecar (the file without its weights) is written beside the output.

Run once per old model file::

    python tools/convert_flat_detector.py OLD.pt NEW.pt
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from fluoronav.detection.config import NETWORK_STAGES, STAGE_ORDER, DetectorConfig
from fluoronav.detection.model import MODEL_FORMAT_VERSION, sidecar_path

__all__ = ["FLAT_DEFAULTS", "RETIRED", "convert_model_file", "declared_from_flat", "is_flat"]

#: the flat settings and their defaults
FLAT_DEFAULTS: dict[str, Any] = {
    "input_size": 128,
    "roi_size": 128,
    "channels": (16, 32, 64, 128, 256),
    "roi_channels": (16, 32, 64, 128, 256),
    "num_res_units": 0,
    "sigma_px": 2.0,
    "heatmap": "softmax",
    "roi_margin_frac": 0.2,
    "roi_min_side_px": 24.0,
    "fine_passes": 2,
    "fine_max_passes": 0,
    "fine_tta": 8,
    "fine_first_tta": None,
    "fine_sure_tta": None,
    "fine_sure_confidence": 0.6,
    "fine_scales": (1.0,),
    "fine_min_separation_px": 0.0,
    "fine_support_px": 0.0,
    "fine_wide_factors": (),
    "fine_wide_min_shift_mm": 5.0,
    "fine_wide_min_gain": 0.15,
    "fine_wide_max_confidence": 1.0,
    "fine_wide_unfound": False,
    "coarse_split": False,
    "coarse_other_min_px": 0,
    "mask_threshold": 0.5,
    "mask_join_frac": 0.0,
    "min_mask_px": 6,
    "min_confidence": 0.3,
    "min_mask_mm2": 0.0,
    "weak_mask_px": 0,
    "weak_min_confidence": 0.15,
    "low_pct": 1.0,
    "high_pct": 99.0,
    "coarse_min_field_mm": 0.0,
    "padded_min_confidence": 0.0,
    "min_edge_ratio": 0.0,
    "unsure_below_confidence": 0.0,
    "unsure_min_edge_ratio": 0.0,
    "free_end_max_continuation": 0.0,
    "free_end_min_confidence": 0.0,
    "shaft_cut_min_mm": 0.0,
    "shaft_cut_run_mm": 3.0,
    "shaft_min_cm_logit": 0.0,
    "bf16_stages": (),
    "refine_channels": (),
    "refine_shape": (48, 80),
    "refine_step_mm": 0.291,
    "refine_sigma_px": 1.5,
    "refine_prior_px": 3.0,
    "refine_shifts_px": (0.0,),
    "refine_tta": 2,
    "refine_assumed_spacing_mm": 0.582,
    "ends_channels": (),
    "ends_shape": (80, 64),
    "ends_inner_px": 8.0,
    "ends_tta": 2,
    "tube_channels": (),
    "shaft_channels": (),
    "tube_spacing_px": 16.0,
    "tube_band_px": 16.0,
}

#: flat settings of stages fluoronav no longer has: left out
RETIRED = frozenset(
    {
        "fine_flip_tta",
        "strip_channels",
        "strip_shape",
        "strip_sigma_px",
        "apex_max_confidence",
        "apex_min_offset_mm",
        "apex_window_mm",
        "apex_start_max_prob",
        "apex_path_start_max_prob",
        "apex_min_prob",
    }
)

#: the settings whose value 0 switches a check off (they must not be negative)
_SWITCHES = (
    "free_end_max_continuation",
    "shaft_cut_min_mm",
    "min_edge_ratio",
    "unsure_below_confidence",
    "unsure_min_edge_ratio",
)


def is_flat(d: Mapping[str, Any]) -> bool:
    """Whether a configuration dictionary has the flat form (a flat key other than ``bf16_stages``)."""
    return any(k in FLAT_DEFAULTS or k in RETIRED for k in d if k != "bf16_stages")


def _network(f: Mapping[str, Any], channels: Any) -> dict[str, Any]:
    return {"channels": list(channels), "num_res_units": f["num_res_units"]}


def _decoder(f: Mapping[str, Any], **kw: Any) -> dict[str, Any]:
    return {"heatmap": f["heatmap"], "sigma_px": f["sigma_px"], "mask_threshold": f["mask_threshold"], **kw}


def _coarse_and_fine(f: Mapping[str, Any]) -> dict[str, Any]:
    """The always-listed stages and the acceptance rules."""
    pct = {"low_pct": f["low_pct"], "high_pct": f["high_pct"]}
    return {
        "assumed_spacing_mm": f["refine_assumed_spacing_mm"],
        "accept": {
            "min_confidence": f["min_confidence"],
            "weak_min_confidence": f["weak_min_confidence"],
            "padded_min_confidence": f["padded_min_confidence"],
            "min_mask_mm2": f["min_mask_mm2"],
        },
        "coarse": {
            "network": _network(f, f["channels"]),
            "sampler": {"size": f["input_size"], "min_field_mm": f["coarse_min_field_mm"], **pct},
            "decoder": _decoder(f, min_mask_px=f["min_mask_px"], weak_mask_px=f["weak_mask_px"]),
        },
        "fine": {
            "network": _network(f, f["roi_channels"]),
            "sampler": {
                "size": f["roi_size"],
                "margin_frac": f["roi_margin_frac"],
                "min_side_px": f["roi_min_side_px"],
                "scales": list(f["fine_scales"]),
                **pct,
            },
            "passes": {
                "passes": f["fine_passes"],
                "max_passes": f["fine_max_passes"],
                "tta": f["fine_tta"],
                "first_tta": f["fine_first_tta"],
                "sure_tta": f["fine_sure_tta"],
                "sure_confidence": f["fine_sure_confidence"],
            },
            "decoder": _decoder(
                f,
                min_separation_px=f["fine_min_separation_px"],
                support_px=f["fine_support_px"],
                join_frac=f["mask_join_frac"],
            ),
            "hypotheses": {
                "coarse_split": f["coarse_split"],
                "coarse_other_min_px": f["coarse_other_min_px"],
                "wide_factors": list(f["fine_wide_factors"]),
                "wide_min_shift_mm": f["fine_wide_min_shift_mm"],
                "min_gain": f["fine_wide_min_gain"],
                "wide_max_confidence": f["fine_wide_max_confidence"],
                "wide_unfound": f["fine_wide_unfound"],
            },
        },
    }


def _patch_stages(f: Mapping[str, Any]) -> dict[str, Any]:
    """The patch networks a flat configuration switches on (those with channels)."""
    patch = {"shape": list(f["ends_shape"]), "step_mm": f["refine_step_mm"]}
    out: dict[str, Any] = {}
    if f["refine_channels"]:
        out["refine"] = {
            "network": _network(f, f["refine_channels"]),
            "sampler": {
                "shape": list(f["refine_shape"]),
                "step_mm": f["refine_step_mm"],
                "shifts_px": list(f["refine_shifts_px"]),
            },
            "decoder": {"sigma_px": f["refine_sigma_px"], "prior_px": f["refine_prior_px"]},
            "tta": f["refine_tta"],
        }
    if f["tube_channels"]:
        out["tube"] = {
            "network": _network(f, f["tube_channels"]),
            "sampler": {**patch, "spacing_px": f["tube_spacing_px"]},
            "band_px": f["tube_band_px"],
            "tta": f["ends_tta"],
        }
    if f["ends_channels"]:
        out["ends"] = {
            "network": _network(f, f["ends_channels"]),
            "sampler": patch,
            "inner_px": f["ends_inner_px"],
            "tta": f["ends_tta"],
        }
    return out


def _checks(f: Mapping[str, Any]) -> dict[str, Any]:
    """The checks a flat configuration switches on (those with a threshold above 0)."""
    out: dict[str, Any] = {}
    if f["free_end_max_continuation"] > 0.0:
        out["free_end"] = {
            "max_continuation": f["free_end_max_continuation"],
            "min_confidence": f["free_end_min_confidence"],
        }
    if f["shaft_channels"] and f["shaft_cut_min_mm"] > 0.0:
        out["shaft"] = {
            "network": _network(f, f["shaft_channels"]),
            "sampler": {
                "shape": list(f["ends_shape"]),
                "step_mm": f["refine_step_mm"],
                "spacing_px": f["tube_spacing_px"],
            },
            "band_px": f["tube_band_px"],
            "tta": f["ends_tta"],
            "cut_min_mm": f["shaft_cut_min_mm"],
            "cut_run_mm": f["shaft_cut_run_mm"],
            "min_cm_logit": f["shaft_min_cm_logit"],
        }
    if f["min_edge_ratio"] > 0.0 or (f["unsure_below_confidence"] > 0.0 and f["unsure_min_edge_ratio"] > 0.0):
        out["edge"] = {
            "min_ratio": f["min_edge_ratio"],
            "unsure_below_confidence": f["unsure_below_confidence"],
            "unsure_min_ratio": f["unsure_min_edge_ratio"],
        }
    return out


def declared_from_flat(flat: Mapping[str, Any]) -> dict[str, Any]:
    """The declared form (:meth:`~fluoronav.detection.config.DetectorConfig.to_dict`'s) of a model
    file's flat configuration; validation is left to the declared config.

    Args:
        flat: flat settings; missing ones take :data:`FLAT_DEFAULTS`, but for a missing ``heatmap``:
            ``"gaussian"``. Unknown and retired keys, and names in ``bf16_stages`` of networks
            fluoronav does not have, are left out.

    Raises:
        ValueError: a check's switch below 0.
    """
    f = {**FLAT_DEFAULTS, **{k: v for k, v in flat.items() if k in FLAT_DEFAULTS}}
    if "heatmap" not in flat:
        f["heatmap"] = "gaussian"
    for name in _SWITCHES:
        if not float(f[name]) >= 0.0:
            raise ValueError(f"{name} must be 0 (off) or more, got {f[name]}")
    out = {**_coarse_and_fine(f), **_patch_stages(f), **_checks(f)}
    out["stages"] = [s for s in STAGE_ORDER if s in ("coarse", "fine") or s in out]
    out["bf16_stages"] = [s for s in f["bf16_stages"] if s in NETWORK_STAGES]
    return out


def convert_model_file(src: Path, dst: Path) -> DetectorConfig:
    """Write ``dst`` (format 2, with its JSON sidecar) from the model file ``src`` of format 1.

    Returns:
        the declared configuration written.

    Raises:
        ValueError: ``src`` is not a model file of format 1.
    """
    blob = torch.load(src, map_location="cpu", weights_only=True)
    if not isinstance(blob, dict) or "state_dict" not in blob or "config" not in blob:
        raise ValueError(f"{src}: not a fluoronav detector model (no state_dict/config)")
    if int(blob.get("format_version", 0)) >= 2 or not (is_flat(blob["config"]) or not blob["config"]):
        raise ValueError(f"{src}: not a model file of format 1 (format {blob.get('format_version')})")
    config = DetectorConfig.model_validate(declared_from_flat(blob["config"]))
    listed = config.network_stages
    # the entries keep their order; the weights of networks not listed are left out
    out = {k: v for k, v in blob.items() if k != "state_dict"}
    out.update(format_version=MODEL_FORMAT_VERSION, config=config.to_dict())
    state = {k: v for k, v in blob["state_dict"].items() if k.split(".", 1)[0] in listed}
    torch.save({**out, "state_dict": state}, dst)
    sidecar_path(dst).write_text(json.dumps(out, indent=2) + "\n", encoding="utf-8")
    return config


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("src", type=Path, help="model file of format 1")
    parser.add_argument("dst", type=Path, help="model file of format 2 to write (and its .json sidecar)")
    args = parser.parse_args()
    config = convert_model_file(args.src, args.dst)
    print(f"{args.dst}: format {MODEL_FORMAT_VERSION}, stages {', '.join(config.stages)}")


if __name__ == "__main__":
    main()
