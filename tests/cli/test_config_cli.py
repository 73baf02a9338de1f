"""``fluoronav config show`` and ``--config FILE``: the defaults written as a site's settings file
load back; a site's file with a misspelled key stops a command with one line naming it."""

from __future__ import annotations

from pathlib import Path

import pytest

from fluoronav.cli.main import main
from fluoronav.navigation.config import NavigationConfig
from fluoronav.settings import load_settings


def test_config_show_prints_the_defaults_and_they_load_back(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    main(["config", "show"])
    text = capsys.readouterr().out
    assert "max_joint_motion_deg = 30.0" in text and "# no joint of a command may turn by more (deg" in text
    site = tmp_path / "site.toml"
    site.write_text(text, encoding="utf-8")
    assert load_settings(NavigationConfig(), site) == NavigationConfig()


def test_config_show_out_writes_the_file(tmp_path: Path) -> None:
    main(["config", "show", "--out", str(tmp_path / "site.toml")])
    loaded = load_settings(NavigationConfig(device="cuda", seed=4), tmp_path / "site.toml")
    assert loaded == NavigationConfig(device="cuda", seed=4)


@pytest.mark.parametrize(
    "command",
    [
        ["navigate", "no_case.json", "--out", "o"],
        ["demo", "--out", "o"],
        ["study", "navigation", "--trials", "1", "--seed", "0", "--out", "o"],
    ],
)
def test_a_misspelled_key_stops_the_command_in_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], command: list[str]
) -> None:
    """Before anything runs (no case is read, no study directory made)."""
    monkeypatch.chdir(tmp_path)
    site = tmp_path / "site.toml"
    site.write_text("[safety]\nmax_jont_motion_deg = 20\n", encoding="utf-8")
    with pytest.raises(SystemExit) as exc:
        main([*command, "--config", str(site), "--device", "cpu"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        f"error: {site}: key safety.max_jont_motion_deg: unknown setting "
        "(did you mean safety.max_joint_motion_deg?)"
    )
    assert not (tmp_path / "o").exists()
