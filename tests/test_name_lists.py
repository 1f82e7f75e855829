"""rig.name_lists: the flag lists "rgb", "r,g" and "a, b" read back as the names given."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from rig.errors import UsageError
from rig.name_lists import chosen_names, split_names

_NAME = st.text(st.characters(blacklist_categories=("Zs", "Cc"), blacklist_characters=",\u2028\u2029\x85"),
                min_size=1, max_size=12).filter(lambda s: s.strip() == s)


@given(st.lists(_NAME, min_size=2, max_size=6), st.sampled_from([",", ", ", " ,", " , "]))
def test_a_comma_list_reads_back_its_names(names: list[str], sep: str) -> None:
    assert split_names(sep.join(names)) == names
    assert split_names(sep.join(names), letters=False) == names


@given(st.lists(_NAME.filter(lambda s: len(s) == 1), min_size=1, max_size=6))
def test_letters_are_one_name_each_and_a_single_name_is_one_without_letters(letters: list[str]) -> None:
    joined = "".join(letters)
    assert split_names(joined) == letters
    assert split_names(f" {joined} ", letters=False) == [joined]


def test_blank_entries_are_dropped_so_an_empty_list_names_nothing() -> None:
    assert split_names(",") == [] and split_names(" , ,") == [] and split_names("  ") == []
    assert split_names("r,,g,") == ["r", "g"] and split_names("r g") == ["r", "g"]


@given(st.lists(_NAME, min_size=1, max_size=6, unique=True), st.booleans())
def test_chosen_names_reads_a_valid_list_back_and_none_when_left_out(names: list[str], letters: bool) -> None:
    assert chosen_names("--x", ",".join(names) + ",", names, letters=letters) == names
    assert chosen_names("--x", None, names) is None


@pytest.mark.parametrize(("spec", "said"), [
    (",", "--filters ',': names nothing; give e.g. --filters rgb, or leave the flag out for all"),
    ("", "names nothing"),
    (" , ", "names nothing"),
    ("rgr", "--filters 'rgr': filter 'r' is named twice; name each once"),
    ("r, g ,r", "filter 'r' is named twice"),
    ("rgx", "--filters 'rgx': unknown filter 'x'; choose from r, g, b (the configuration rig.yaml)"),
    ("r,ir", "unknown filter 'ir'"),
])
def test_chosen_names_refuses_with_one_line_that_says_what_and_how(spec: str, said: str) -> None:
    with pytest.raises(UsageError) as e:
        chosen_names("--filters", spec, ["r", "g", "b"], what="filter", where="the configuration rig.yaml")
    assert said in str(e.value) and "\n" not in str(e.value)


def test_chosen_names_leaves_unknown_names_to_the_caller_without_choices() -> None:
    assert chosen_names("--channels", "r g b", what="channel") == ["r", "g", "b"]
    assert chosen_names("--effects", "lens_blur", letters=False) == ["lens_blur"]
