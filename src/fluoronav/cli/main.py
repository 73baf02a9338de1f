"""The ``fluoronav`` command line.

Each command lives in its own module of this package and exposes ``register(app)``; this module
assembles them and turns :class:`~fluoronav.errors.InputError` into one line on stderr and exit
status 2 (no traceback for user errors).
"""

from __future__ import annotations

import importlib
import logging
import sys

import typer

from fluoronav import __version__
from fluoronav.errors import FluoronavError, InputError

#: command modules, in the order their commands appear in ``--help``
COMMAND_MODULES = (
    "demo",
    "navigate",
    "render",
    "simulate",
    "train",
    "detect",
    "evaluate",
    "study",
    "deepfluoro",
    "register",
    "calibrate",
    "report",
    "bench",
    "config",
)

app = typer.Typer(
    name="fluoronav",
    help="Fluoroscopic navigation of a surgical robot with a continuum manipulator.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"fluoronav {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(
        False, "--version", callback=_version, is_eager=True, help="Print the version."
    ),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log progress details to stderr."),
) -> None:
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s"
    )


def _register_all() -> None:
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(f"fluoronav.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"fluoronav.cli.{name}":
                continue  # command not built yet
            raise
        module.register(app)


_register_all()


def main(argv: list[str] | None = None) -> None:
    """Entry point: run the app, reporting user errors in one line."""
    try:
        # without standalone mode click returns a command's exit status instead of exiting with it
        code = app(args=argv, standalone_mode=False)
    except InputError as exc:
        typer.echo(f"error: {exc}", err=True)
        sys.exit(2)
    except FluoronavError as exc:
        typer.echo(f"error: {exc}", err=True)
        sys.exit(1)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except typer.Abort:
        typer.echo("aborted", err=True)
        sys.exit(130)
    except OSError as exc:
        # a file the user named could not be read or written: say which, in one line
        where = exc.filename if exc.filename is not None else "file"
        typer.echo(f"error: {where}: {exc.strerror or exc}", err=True)
        sys.exit(1)
    except KeyboardInterrupt:
        typer.echo("interrupted; finished results are kept on disk", err=True)
        sys.exit(130)
    except Exception as exc:
        if isinstance(exc, _usage_errors()):
            exc.show()  # type: ignore[attr-defined]
            sys.exit(exc.exit_code)  # type: ignore[attr-defined]
        raise
    if isinstance(code, int) and code != 0:
        sys.exit(code)


def _usage_errors() -> tuple[type[Exception], ...]:
    """Usage-error classes: click's, and those of the click copy that typer >= 0.2x carries."""
    import click  # optional: typer no longer needs click; only on a usage error

    typer_error = getattr(typer, "TyperException", None)  # absent before typer carried click
    return (click.ClickException,) if typer_error is None else (click.ClickException, typer_error)
