"""The declaration of a query's fields is consistent: one entry per name, defaults only where a
push may leave a field out, provenance that a pushed pair always carries."""

from __future__ import annotations

from typing import get_args

from runvocab.query_fields import PROVENANCE, QUERY_FIELD_NAMES, QUERY_FIELDS, FieldType

DEFAULT_TYPES = {"bool": bool, "int": int}


def test_each_field_is_declared_once_with_a_known_type_and_a_description() -> None:
    assert len(set(QUERY_FIELD_NAMES)) == len(QUERY_FIELDS)
    trainer = [field.trainer for field in QUERY_FIELDS if field.trainer is not None]
    assert len(set(trainer)) == len(trainer)
    for field in QUERY_FIELDS:
        assert field.type in get_args(FieldType), field.name
        assert field.description and field.description == field.description.strip(), field.name


def test_only_an_optional_field_has_a_default_and_it_has_the_fields_type() -> None:
    for field in QUERY_FIELDS:
        if field.default is None:
            assert field.nullable == field.optional, field.name
            continue
        assert field.optional and not field.nullable, field.name
        assert type(field.default) is DEFAULT_TYPES[field.type], field.name


def test_provenance_is_the_pair_itself_and_every_push_carries_it() -> None:
    assert set(PROVENANCE) == {"segment_length", "first_trajectory", "first_start",
                               "second_trajectory", "second_start"}
    for name in PROVENANCE:
        field = QUERY_FIELDS[QUERY_FIELD_NAMES.index(name)]
        assert field.type == "int" and not field.optional, name


def test_the_two_sides_are_declared_alike() -> None:
    first = [field for field in QUERY_FIELDS if field.name.startswith("first_")]
    second = [field for field in QUERY_FIELDS if field.name.startswith("second_")]
    assert [f.name.removeprefix("first_") for f in first] == [
        f.name.removeprefix("second_") for f in second]
    for a, b in zip(first, second, strict=True):
        assert (a.type, a.optional, a.provenance, a.exported) == (
            b.type, b.optional, b.provenance, b.exported), a.name
        assert a.description.replace("first", "second") == b.description, a.name
        if a.trainer is not None:
            assert b.trainer == a.trainer.replace("0", "1"), a.name
