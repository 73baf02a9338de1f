"""Settings files over frozen dataclasses (``fluoronav.settings``): overrides by dotted path or table,
nested and optional dataclasses, tuples and arrays of tables, types and ranges checked, one-line
errors; the written TOML and JSON."""

from __future__ import annotations

import dataclasses
import json
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Literal

import pytest

from fluoronav.errors import InputError
from fluoronav.settings import apply_settings, load_settings, setting, settings_dict, settings_toml


@dataclass(frozen=True)
class Level:
    """A level.

    Attributes:
        sigma: steps per parameter.
        popsize: the population.
    """

    sigma: tuple[float, ...]
    popsize: int = setting(10, "population", ge=1)
    name: str = "x"


@dataclass(frozen=True)
class Inner:
    gain_db: float = setting(1.0, "gain", unit="dB", ge=0, le=10)
    mode: Literal["a", "b"] = "a"
    span: tuple[float, float] = setting((0.1, 0.9), "span", ge=0)
    label: str = setting("a", "label")


@dataclass(frozen=True)
class Root:
    derived_settings: ClassVar[dict[str, str]] = {"inner.label": "set from the input"}

    device: str = setting("cpu", "device", site=False)
    count: int = setting(3, "count", ge=0)
    flag: bool = setting(True, "flag")
    limit_mm: float | None = setting(None, "limit; none: none", unit="mm", gt=0)
    inner: Inner = setting(default_factory=Inner, doc="inner")
    maybe: Inner | None = None
    levels: tuple[Level, ...] = (Level((1.0, 2.0)), Level((3.0,), popsize=5, name="second"))


def _apply(text: str) -> Root:
    return apply_settings(Root(), tomllib.loads(text), source="site.toml")


def test_dotted_keys_and_tables_set_the_same() -> None:
    dotted = _apply("count = 5\ninner.gain_db = 2\ninner.span = [0.2, 0.8]\n")
    table = _apply('count = 5\n[inner]\ngain_db = 2.0\nspan = [0.2, 0.8]\nmode = "a"\n')
    assert dotted == table == Root(count=5, inner=Inner(gain_db=2.0, span=(0.2, 0.8)))
    assert isinstance(dotted.inner.gain_db, float) and isinstance(dotted.inner.span, tuple)
    assert _apply("") == Root()


def test_an_array_of_tables_replaces_a_tuple_each_element_on_the_default_of_its_index() -> None:
    one = _apply("[[levels]]\npopsize = 7\n")
    assert one.levels == (Level((1.0, 2.0), popsize=7),)
    three = _apply("[[levels]]\n[[levels]]\nsigma = [4.0]\n[[levels]]\nsigma = [5.0, 6.0]\n")
    assert three.levels == (Level((1.0, 2.0)), Level((4.0,), popsize=5, name="second"), Level((5.0, 6.0)))
    with pytest.raises(InputError, match=r"key levels\[2\]: is none: a table that sets it must give sigma"):
        _apply("[[levels]]\n[[levels]]\n[[levels]]\npopsize = 2\n")


def test_none_and_optional_tables() -> None:
    assert _apply('limit_mm = "none"').limit_mm is None
    assert _apply("limit_mm = 40").limit_mm == 40.0
    assert _apply("[maybe]\ngain_db = 2\n").maybe == Inner(gain_db=2.0)  # built on Inner's defaults
    with_maybe = dataclasses.replace(Root(), maybe=Inner(gain_db=3.0))
    assert apply_settings(with_maybe, {"maybe": "none"}).maybe is None


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("count = 1.5", "key count: an integer expected, got 1.5"),
        ("flag = 1", "key flag: true or false expected, got 1"),
        ('inner.gain_db = "x"', "key inner.gain_db: a number expected, got 'x'"),
        ("inner.gain_db = 11", "key inner.gain_db: 11 dB is out of range (must be at most 10 dB)"),
        ("limit_mm = 0", "key limit_mm: 0 mm is out of range (must be more than 0 mm)"),
        ("inner.span = [0.1]", "key inner.span: an array of 2 values expected, got 1"),
        ("inner.span = [-1, 0.5]", "key inner.span[0]: -1 is out of range (must be at least 0)"),
        ('inner.mode = "c"', "key inner.mode: one of 'a', 'b' expected, got 'c'"),
        ("inner = 3", "key inner: a table of Inner settings expected, got 3"),
        ("count = [1]", "key count: an integer expected, got an array"),
        ("cuont = 1", "key cuont: unknown setting (did you mean count?)"),
        ("gain_db = 1", "key gain_db: unknown setting (did you mean inner.gain_db?)"),
        ("inner.gian_db = 1", "key inner.gian_db: unknown setting (did you mean inner.gain_db?)"),
        ("zzz = 1", "key zzz: unknown setting"),
        ('device = "cuda"', "key device: not a site setting (a run's own option, set on the command line)"),
        ('inner.label = "b"', "key inner.label: not a site setting (set from the input)"),
    ],
)
def test_a_bad_key_is_one_line_naming_the_file_and_the_key(text: str, message: str) -> None:
    with pytest.raises(InputError) as info:
        _apply(text)
    assert str(info.value) == f"site.toml: {message}"


def test_a_missing_or_malformed_file_names_it(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="settings file not found"):
        load_settings(Root(), tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("count = = 2\n", encoding="utf-8")
    with pytest.raises(InputError, match=r"bad.toml: not valid TOML") as info:
        load_settings(Root(), bad)
    assert len(str(info.value).splitlines()) == 1
    good = tmp_path / "good.toml"
    good.write_text("[inner]\ngain_db = 4\n", encoding="utf-8")
    assert load_settings(Root(), good).inner.gain_db == 4.0


def test_settings_dict_is_json_ready_without_the_derived_settings() -> None:
    d = settings_dict(Root())
    assert d["device"] == "cpu" and d["inner"] == {"gain_db": 1.0, "mode": "a", "span": [0.1, 0.9]}
    assert d["levels"][1] == {"sigma": [3.0], "popsize": 5, "name": "second"} and d["maybe"] is None
    json.dumps(d, allow_nan=False)


def test_the_written_toml_loads_back_to_an_equal_tree() -> None:
    trees = [Root(), Root(count=0, limit_mm=2.5, maybe=Inner(mode="b"), levels=()), Root(flag=False)]
    for tree in trees:
        text = settings_toml(tree, title="a title\nover two lines")
        back = apply_settings(Root(), tomllib.loads(text))
        assert back == tree and repr(back) == repr(tree)
    text = settings_toml(Root())
    assert "# gain (dB, >= 0, <= 10)\ngain_db = 1.0" in text
    assert "# steps per parameter\nsigma = [1.0, 2.0]" in text  # from the class docstring
    assert "\nlabel" not in text and "# device: device; set by the run, not here" in text
    assert 'limit_mm = "none"' in text


def test_the_navigation_tree_written_as_toml_loads_back() -> None:
    from fluoronav.navigation.checks.preflight_config import PreflightConfig
    from fluoronav.navigation.config import NavigationConfig
    from fluoronav.registration.bone.presets import FEMUR_MULTI_VIEW_PRESET

    default = NavigationConfig()
    changed = dataclasses.replace(
        default,
        preflight=None,
        views=dataclasses.replace(default.views, femur=FEMUR_MULTI_VIEW_PRESET, max_cm_starts=1),
    )
    site = dataclasses.replace(default, preflight=PreflightConfig(max_insertion_depth_mm=80.0))
    for tree in (default, changed, site):
        back = apply_settings(NavigationConfig(), tomllib.loads(settings_toml(tree)))
        assert back == tree and repr(back) == repr(tree)


def test_every_declared_setting_is_written_with_its_comment() -> None:
    """Every key of the sections declared with ``setting`` has its one-line doc above it."""
    from fluoronav.navigation.config import NavigationConfig

    lines = settings_toml(NavigationConfig()).splitlines()
    section = ""
    for k, line in enumerate(lines):
        if line.startswith("["):
            section = line.strip("[]")
        elif (
            line
            and not line.startswith("#")
            and section in ("", "safety", "safety.cm", "preflight", "verification")
        ):
            assert lines[k - 1].startswith("# "), line
