"""The detection benchmark returns its contract keys (timings are not asserted: shared CPU)."""

from __future__ import annotations

import math

import pytest

from fluoronav.bench import detection as bench


@pytest.mark.slow
def test_bench_quick_returns_contract_keys() -> None:
    result = bench.run(quick=True)
    keys = {"detect_ms", "detect_ms_baseline", "detect_ms_speedup"}
    config = bench.Detector.load(device="cpu").config if bench.shipped_model_path().is_file() else None
    if config is not None and config.fine.hypotheses.wide_factors:  # its second look
        keys |= {"detect_second_look_ms", "detect_second_look_ms_baseline", "detect_second_look_ms_speedup"}
    if config is not None and config.bf16_stages and bench.native_bf16():  # the bfloat16 pipeline
        keys |= {"detect_bfloat16_ms", "detect_bfloat16_ms_baseline", "detect_bfloat16_ms_speedup"}
    assert set(result) == keys
    assert all(math.isfinite(v) and v > 0 for v in result.values())
    assert result["detect_ms_speedup"] == pytest.approx(result["detect_ms_baseline"] / result["detect_ms"])
