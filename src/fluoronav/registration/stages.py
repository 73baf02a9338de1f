"""Stage records: what each stage of a registration chain took, whether it passed, and its
diagnostics (JSON-ready), kept by a recorder the caller gives (:data:`StageRecorder`)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass, field
from typing import Any

__all__ = ["StageRecord", "StageRecorder", "timed_stages", "unrecorded"]


@dataclass
class StageRecord:
    """One stage's record: wall time, whether its checks passed, and its diagnostics (JSON-ready)."""

    seconds: float = 0.0
    passed: bool = True
    diagnostics: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {"seconds": self.seconds, "passed": self.passed, **self.diagnostics}


#: ``recorder(stage_name)``: a context manager around one stage that yields its :class:`StageRecord`
#: (the stage fills ``diagnostics`` and clears ``passed`` where it refuses); the recorder times it
#: and may tell a progress display. Stage names: "pelvis", "femur", "cm".
StageRecorder = Callable[[str], AbstractContextManager[StageRecord]]


def timed_stages(records: dict[str, StageRecord]) -> StageRecorder:
    """A :data:`StageRecorder` that times each stage into ``records[name]``."""

    @contextmanager
    def stage(name: str) -> Iterator[StageRecord]:
        rec = records.setdefault(name, StageRecord())
        t0 = time.perf_counter()
        try:
            yield rec
        finally:
            rec.seconds = time.perf_counter() - t0

    return stage


@contextmanager
def unrecorded(name: str) -> Iterator[StageRecord]:
    """A :data:`StageRecorder` that keeps nothing."""
    yield StageRecord()
