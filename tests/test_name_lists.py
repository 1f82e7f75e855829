"""rig.name_lists: the flag lists "rgb", "r,g" and "a, b" read back as the names given."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from rig.name_lists import split_names

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
