"""Registration traces: per-iteration optimiser records and per-level summaries, JSON-serialisable."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from fluoronav.registration.optimizer import IterationRecord

__all__ = ["LevelTrace", "RegistrationTrace"]


def _clean(obj: Any) -> Any:
    """Make a JSON-safe copy: tuples → lists, non-finite floats → None (strict JSON)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_clean(v) for v in obj]
    return obj


@dataclass
class LevelTrace:
    """One level: its settings, every iteration and the outcome.

    Attributes:
        index, name: position in the level list and label.
        config: the level's settings (``LevelConfig.to_dict()``).
        x_start: parameters the level started from; x, cost: best found.
        iterations: per-iteration records (best/mean cost, σ, best params, evaluations, elapsed s).
        n_evals, n_iters, converged, stop_reason, seconds, n_nonfinite: run summary.
    """

    index: int
    name: str
    config: dict[str, Any]
    x_start: list[float]
    x: list[float] = field(default_factory=list)
    cost: float = math.nan
    n_evals: int = 0
    n_iters: int = 0
    converged: bool = False
    stop_reason: str = ""
    seconds: float = 0.0
    n_nonfinite: int = 0
    iterations: list[IterationRecord] = field(default_factory=list)


@dataclass
class RegistrationTrace:
    """The whole registration: parameter names and one :class:`LevelTrace` per level; ``screened``:
    the runs of a multi-start that were not chosen (first levels not continued, then the levels of
    continued runs that lost on the final cost)."""

    parameter_names: list[str]
    levels: list[LevelTrace] = field(default_factory=list)
    screened: list[LevelTrace] = field(default_factory=list)

    @property
    def n_evals(self) -> int:
        return sum(lv.n_evals for lv in self.levels)

    def to_dict(self) -> dict[str, Any]:
        return _clean(asdict(self))

    def to_json(self, path: str | Path | None = None, *, indent: int | None = 1) -> str:
        """JSON text (strict: NaN/inf written as null); also written to ``path`` when given."""
        text = json.dumps(self.to_dict(), indent=indent, allow_nan=False)
        if path is not None:
            Path(path).write_text(text, encoding="utf-8")
        return text

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RegistrationTrace:
        def num(v: Any) -> float:
            return math.nan if v is None else float(v)

        def level(lv: dict[str, Any]) -> LevelTrace:
            its = [
                IterationRecord(
                    **{
                        **it,
                        "best_params": tuple(num(v) for v in it["best_params"]),
                        "best_cost": num(it["best_cost"]),
                        "mean_cost": num(it["mean_cost"]),
                        "sigma": num(it["sigma"]),
                    }
                )
                for it in lv["iterations"]
            ]
            return LevelTrace(**{**lv, "cost": num(lv["cost"]), "iterations": its})

        return cls(
            parameter_names=list(d["parameter_names"]),
            levels=[level(lv) for lv in d["levels"]],
            screened=[level(lv) for lv in d.get("screened", [])],
        )

    @classmethod
    def from_json(cls, text: str) -> RegistrationTrace:
        return cls.from_dict(json.loads(text))
