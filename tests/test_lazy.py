"""``fluoronav.lazy``: a face imports its names' modules on first use, read from its TYPE_CHECKING block."""

from __future__ import annotations

import subprocess
import sys

from fluoronav.lazy import type_checking_imports


def test_the_type_checking_block_gives_the_exports() -> None:
    source = (
        "from typing import TYPE_CHECKING\n"
        "from fluoronav.lazy import lazy_face\n"
        "if TYPE_CHECKING:\n"
        "    from p.a import A, b\n"
        "    from p.c import C as D\n"
        "    from p.a import e\n"
        "from p.x import not_exported\n"
    )
    assert type_checking_imports(source) == {"p.a": ["A", "b", "e"], "p.c": ["D"]}


def test_a_face_imports_a_module_on_first_use_only() -> None:
    # the geometry face's se3 is a light module (numpy only): the process stays short
    module = "fluoronav.geometry.se3"
    code = (
        "import sys\n"
        "import fluoronav.geometry as face\n"
        f"before = {module!r} in sys.modules\n"
        "face.se3.make\n"
        f"print(before, {module!r} in sys.modules, 'se3' in dir(face), 'torch' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "True", "True", "False"]
