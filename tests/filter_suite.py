"""The FilterChanger interface suite, run against every implementation.

A test module subclasses :class:`FilterChangerSuite` and provides two fixtures:

- ``changer``: an open FilterChanger configured with :data:`POSITIONS`;
- ``activity``: a callable returning how many interactions with the device
  (bytes written, operator prompts) happened so far.
"""

from __future__ import annotations

from collections.abc import Callable

import pytest

from drivers.errors import ParameterError, StateError
from drivers.interfaces import FilterChanger

POSITIONS = {"r": 1, "g": 2, "b": 3}


class FilterChangerSuite:
    def test_identity_is_text(self, changer: FilterChanger) -> None:
        ident = changer.identity()
        assert isinstance(ident, str) and ident.strip()

    def test_names_are_the_configured_ones(self, changer: FilterChanger) -> None:
        assert changer.names() == list(POSITIONS)

    def test_select_each_filter_then_current(self, changer: FilterChanger) -> None:
        for name in ["g", "b", "r", "b"]:
            changer.select(name)
            assert changer.current() == name

    def test_select_twice_is_harmless(self, changer: FilterChanger) -> None:
        changer.select("g")
        changer.select("g")
        assert changer.current() == "g"

    @pytest.mark.parametrize("bad", ["x", "R", "", 2, None])
    def test_unknown_filter_refused_before_any_interaction(
        self, changer: FilterChanger, activity: Callable[[], int], bad: object
    ) -> None:
        before = activity()
        with pytest.raises(ParameterError):
            changer.select(bad)  # type: ignore[arg-type]
        assert activity() == before

    def test_closed_changer_refuses(self, changer: FilterChanger) -> None:
        with changer:
            changer.select("r")
        with pytest.raises(StateError):
            changer.select("g")

