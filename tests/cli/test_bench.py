"""``fluoronav bench``: the device option (timings themselves are not asserted: shared machines)."""

from __future__ import annotations

import math

import pytest
import torch

from fluoronav.cli.bench import collect
from fluoronav.cli.main import main


def test_bench_records_its_device() -> None:
    figures = collect(only=["no-such-stage"], device="cpu")  # no stage runs: the record alone
    assert figures["machine"]["device"] == "cpu"


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--only", "rendering", "--device", "tpu"], "unknown device 'tpu'"),
        (["--only", "detect"], "--only: unknown stage 'detect'; use rendering, simulation, detection"),
    ],
)
def test_bench_refuses_bad_options(args: list[str], message: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["bench", *args])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and message in err


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_rendering_bench_runs_on_cuda() -> None:
    figures = collect(quick=True, only=["rendering"], device="cuda")
    assert figures["machine"]["device"].startswith("cuda")
    for key in ("ct_drr_128_ms", "cm_drr_128_ms_per_candidate"):
        assert math.isfinite(figures[key]) and figures[key] > 0
        assert figures[f"{key}_speedup"] == pytest.approx(figures[f"{key}_baseline"] / figures[key])
    assert figures["ct_drr_128_max_rel_diff_vs_baseline"] < 0.05  # the two renders agree (0.014)
