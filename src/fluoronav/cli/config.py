"""``fluoronav config show [--out FILE]``: the navigation's settings as a site's settings file.

The file is TOML, every key with its value, doc and unit (:func:`~fluoronav.settings.settings_toml`).
A site keeps the keys it changes and gives the file to ``fluoronav navigate``, ``fluoronav demo`` or
``fluoronav study navigation`` with ``--config FILE`` (:data:`SETTINGS_OPTION`); docs/data-formats.md
("Site settings").
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import typer

if TYPE_CHECKING:
    from fluoronav.navigation.config import NavigationConfig

SETTINGS_OPTION = typer.Option(
    None,
    "--config",
    metavar="FILE",
    help=(
        "A site's settings file (TOML) over the navigation's defaults, e.g. safety.max_joint_motion_deg "
        "= 20; fluoronav config show writes them all."
    ),
)

_TITLE = """fluoronav {version}: the navigation's settings (fluoronav config show).
Keep the keys you change, delete the rest, and give the file with --config FILE to fluoronav
navigate, demo or study navigation. A key is a dotted path (safety.max_joint_motion_deg = 20) or a
key of a [table]; an array of tables replaces a tuple, each element built on the default of its index."""


def navigation_config(path: Path | None, *, device: str = "cpu", seed: int = 0) -> NavigationConfig:
    """The navigation's settings: the defaults with the run's ``device`` and ``seed``, then the site's
    file ``path`` (None: none).

    Raises:
        InputError: the file, naming the key it cannot apply.
    """
    from fluoronav.navigation.config import NavigationConfig  # lazy: fast --help
    from fluoronav.settings import load_settings  # lazy: fast --help

    cfg = NavigationConfig(device=device, seed=seed)
    return cfg if path is None else load_settings(cfg, path)


def defaults_toml() -> str:
    """The navigation's default settings as a TOML settings file."""
    from fluoronav import __version__
    from fluoronav.navigation.config import NavigationConfig  # lazy: fast --help
    from fluoronav.settings import settings_toml  # lazy: fast --help

    return settings_toml(NavigationConfig(), title=_TITLE.format(version=__version__))


def register(app: typer.Typer) -> None:
    config_app = typer.Typer(
        help="The navigation's settings, as a file a site edits (--config of navigate, demo, study).",
        no_args_is_help=True,
    )

    @config_app.command("show")
    def show(
        out: Path | None = typer.Option(None, "--out", help="Write the file here instead of to stdout."),
    ) -> None:
        """Print the navigation's default settings as a TOML settings file: each key with its value,
        doc, unit and range. Edit a copy and give it with --config FILE."""
        text = defaults_toml()
        if out is None:
            typer.echo(text, nl=False)
            return
        out.write_text(text, encoding="utf-8")
        typer.echo(f"wrote {out}", err=True)

    app.add_typer(config_app, name="config")
