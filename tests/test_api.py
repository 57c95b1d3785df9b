"""The public API's shape: at most 30 top-level names, three namespaces for the rest, the
old top-level names still found (with a warning), and docs/api.md showing every name."""

import inspect
import re
import warnings
from pathlib import Path

import pytest

import jaxspring as js

API_DOC = Path(__file__).resolve().parents[1] / "docs" / "api.md"
NAMESPACES = {"sim": js.sim, "io": js.io, "fitting": js.fitting}


def test_at_most_30_top_level_names_and_every_one_resolves():
    assert len(js.__all__) <= 30, len(js.__all__)
    assert len(set(js.__all__)) == len(js.__all__)
    for name in js.__all__:
        assert getattr(js, name) is not None, name
    for space, module in NAMESPACES.items():
        assert len(set(module.__all__)) == len(module.__all__), space
        for name in module.__all__:
            assert getattr(module, name) is not None, (space, name)
        assert set(module.__all__) <= set(dir(module)), space


def test_a_name_that_moved_is_still_found_with_a_warning_naming_its_place():
    moved = {n: space for space, m in NAMESPACES.items() for n in m.__all__ if n not in js.__all__}
    assert {"make_model", "save_fit", "summarise", "FitProgress", "Drive"} <= set(moved)
    for name, space in moved.items():
        with pytest.warns(DeprecationWarning, match=rf"js\.{name} is now js\.{space}\.{name}"):
            old = getattr(js, name)
        assert old is getattr(NAMESPACES[space], name), name
    with pytest.warns(DeprecationWarning, match="internal"):
        assert js.smooth_horizon.__name__ == "smooth_horizon"
    with pytest.raises(AttributeError, match="no attribute 'not_a_name'"):
        js.not_a_name  # noqa: B018


def test_importing_the_package_warns_of_nothing():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for name in js.__all__:
            getattr(js, name)


def test_no_internal_keyword_is_public():
    # the keywords a fit's own stages pass to the report are not the user's
    assert list(inspect.signature(js.identifiability).parameters) == [
        "scene",
        "observations",
        "names",
        "values",
        "max_parameters",
    ]


def test_the_api_page_shows_every_public_name_in_an_example():
    code = "\n".join(re.findall(r"```python\n(.*?)```", API_DOC.read_text(), flags=re.S))
    shown = set(re.findall(r"\bjs\.((?:sim\.|io\.|fitting\.)?[A-Za-z_][A-Za-z_0-9]*)", code))
    public = set(js.__all__) | {f"{space}.{n}" for space, m in NAMESPACES.items() for n in m.__all__}
    assert public - shown == set()
