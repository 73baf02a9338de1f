"""User-facing errors.

Every problem with user input is raised as :class:`InputError`, which names the file and the
problem. The CLI turns it into one line on stderr and a non-zero exit status, without a traceback.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


class FluoronavError(Exception):
    """Base class of every error fluoronav raises on purpose."""


class InputError(FluoronavError):
    """Bad user input: an unreadable, empty, malformed or inconsistent file or argument.

    Args:
        source: the file (or argument name) at fault.
        problem: what is wrong with it, as a short phrase.
    """

    def __init__(self, source: str | Path, problem: str) -> None:
        # the message is always one line, whatever the input echoed into it (a key, a parser message)
        self.source = str(source).replace("\r", "\\r").replace("\n", "\\n")
        self.problem = " ".join(str(problem).split())
        super().__init__(f"{self.source}: {self.problem}")

    def __reduce__(self) -> tuple[type[InputError], tuple[str, str]]:
        """Pickled with its fields (it crosses process boundaries in studies' workers)."""
        return (type(self), (self.source, self.problem))


class RegistrationFailure(FluoronavError):
    """A registration or calibration that did not converge; carries the reason."""


class RegistrationRefused(FluoronavError):
    """A registration that failed its checks; nothing may act on it.

    Args:
        stage: the stage that refused (e.g. ``"cm"``).
        check: the check that failed (e.g. ``"edge_ncc"``).
        detail: what was measured against which threshold, as a short sentence.
        view: the view concerned, or "".
    """

    def __init__(self, stage: str, check: str, detail: str, view: str = "") -> None:
        self.stage, self.check, self.view, self.detail = stage, check, view, detail
        where = f"stage {stage}" + (f", view {view}" if view else "")
        super().__init__(f"{where}, check {check}: {detail}")

    def __reduce__(self) -> tuple[type[RegistrationRefused], tuple[str, str, str, str]]:
        """Pickled with its fields (it crosses process boundaries in studies' workers)."""
        return (type(self), (self.stage, self.check, self.detail, self.view))


def read_json_object(path: str | Path, *, what: str) -> dict[str, Any]:
    """Read a JSON file that must hold an object; every problem is an :class:`InputError`.

    Args:
        path: the file.
        what: what the file is, for the messages (e.g. ``"case file"``).
    """
    p = Path(path)
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(p, f"{what} not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(p, f"cannot read {what} ({exc.__class__.__name__})") from None
    except json.JSONDecodeError as exc:
        raise InputError(p, f"not valid JSON ({exc.msg} at line {exc.lineno})") from None
    if not isinstance(d, dict):
        raise InputError(p, f"a {what} must be a JSON object")
    return d


def read_text_file(path: str | Path, *, what: str) -> str:
    """The text of a user's file (UTF-8, a BOM allowed); a missing, unreadable or empty file is an
    :class:`InputError` naming it (``what``: e.g. ``"landmark file"``)."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, f"{what} not found")
    try:
        text = p.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(p, f"unreadable {what} ({exc.__class__.__name__})") from None
    if not text.strip():
        raise InputError(p, f"empty {what}")
    return text
