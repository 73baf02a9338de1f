"""Stage records: what each stage of a registration chain took, whether it passed, and its
diagnostics (JSON-ready), kept by a recorder the caller gives (:data:`StageRecorder`), and the one
timer of named stages (:class:`StageTimer`) that the navigation pipeline and its simulation use."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass, field
from typing import Any

__all__ = ["StageRecord", "StageRecorder", "StageTimer", "timed_stages", "unrecorded"]


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


class StageTimer:
    """Times each named stage into ``records[name]`` (a :class:`StageRecord`) and tells
    ``on_stage(name, "start" | "done")`` (a progress display); calling it is a :data:`StageRecorder`."""

    def __init__(
        self,
        records: dict[str, StageRecord] | None = None,
        on_stage: Callable[[str, str], None] | None = None,
    ) -> None:
        self.records = {} if records is None else records
        self.on_stage = on_stage

    @contextmanager
    def __call__(self, name: str) -> Iterator[StageRecord]:
        rec = self.records.setdefault(name, StageRecord())
        if self.on_stage is not None:
            self.on_stage(name, "start")
        t0 = time.perf_counter()
        try:
            yield rec
        finally:
            rec.seconds = time.perf_counter() - t0
            if self.on_stage is not None:
                self.on_stage(name, "done")

    def within(self, prefix: str) -> StageRecorder:
        """The recorder of a chain's stages (a view set's), each named ``prefix + stage`` here."""
        return lambda name: self(prefix + name)


def timed_stages(records: dict[str, StageRecord]) -> StageRecorder:
    """A :data:`StageRecorder` that times each stage into ``records[name]`` (no callback)."""
    return StageTimer(records)


@contextmanager
def unrecorded(name: str) -> Iterator[StageRecord]:
    """A :data:`StageRecorder` that keeps nothing."""
    yield StageRecord()
