"""The entry point: usage errors end in a short message and exit code 2, not a traceback."""

from __future__ import annotations

from pathlib import Path

import pytest

from fluoronav.cli.main import main


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["simulate", "--n", "1", "--out", "x", "--no-such-option"], "No such option"),
        (["no-such-command"], "No such command"),
        (["simulate", "--n", "zero", "--out", "x"], "Invalid value"),
        (
            ["train", "--data", "x", "--out", "m.pt", "--stage", "refine", "--stage", "fine"],
            "'refine', 'ends', 'tube', 'shaft' alone",
        ),
        (["train", "--data", "x", "--out", "m.pt", "--stage", "middle"], "stages must be"),
        (["train", "--data", "x", "--out", "m.pt", "--stage", "shaft"], "give tube_shaft_prob > 0"),
        (["train", "--data", "x", "--out", "m.pt", "--tube-shaft-prob", "0.3"], "stages 'tube' and 'shaft'"),
        (["train", "--data", "x", "--out", "m.pt", "--keep-decoding"], "give --init"),
        (["detect", "x.png", "--out", "o", "--precision", "half"], "--precision: unknown precision 'half'"),
        (["evaluate", "--data", "x", "--precision", "fp16"], "use auto, float32, bfloat16"),
        (["train", "--data", "x", "--out", "m.pt", "--coarse-size", "200"], "multiple of 16"),
        (
            ["train", "--data", "x", "--out", "m.pt", "--coarse-size", "256", "--stage", "fine"],
            "train the coarse stage too",
        ),
        (
            [
                "simulate",
                "--n",
                "1",
                "--out",
                "x",
                "--max-shaft-mm",
                "30",
                "--shaft-length-mm",
                "0",
            ],
            "needs a shaft",
        ),
        (
            ["simulate", "--n", "1", "--out", "x", "--max-shaft-angle-deg", "60", "--shaft-length-mm", "0"],
            "max_shaft_angle_deg needs a shaft",
        ),
    ],
)
def test_usage_error_is_short(args: list[str], message: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(args)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert message in err
    assert "Traceback" not in err
    assert len(err.strip().splitlines()) <= 4


def test_an_os_error_on_a_named_file_is_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import fluoronav.cli.main as cli_main

    def fail(*args: object, **kwargs: object) -> None:
        raise PermissionError(13, "Permission denied", str(tmp_path / "out.json"))

    monkeypatch.setattr(cli_main, "app", fail)
    with pytest.raises(SystemExit) as exc:
        main(["anything"])
    assert exc.value.code == 1
    err = capsys.readouterr().err.strip()
    assert err == f"error: {tmp_path / 'out.json'}: Permission denied"
