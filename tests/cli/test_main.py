"""The entry point: usage errors end in a short message and exit code 2, not a traceback."""

from __future__ import annotations

import pytest

from fluoronav.cli.main import main


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["simulate", "--n", "1", "--out", "x", "--no-such-option"], "No such option"),
        (["no-such-command"], "No such command"),
        (["simulate", "--n", "zero", "--out", "x"], "Invalid value"),
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
