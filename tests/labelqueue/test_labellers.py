"""Labellers authenticate with a bearer token that the database stores only as a hash."""

from __future__ import annotations

import hashlib

import pytest
from sqlalchemy import select, text
from sqlalchemy.orm import Session

from labelqueue import (
    Conflict,
    Labeller,
    NotFound,
    Role,
    authenticate,
    create_labeller,
    labeller_names,
    rotate_token,
    set_labeller_active,
    update_labeller,
)


def test_right_token_authenticates_and_wrong_ones_do_not(session: Session) -> None:
    alice, alice_token = create_labeller(session, name="alice")
    bob, bob_token = create_labeller(session, name="bob", role=Role.OPERATOR)

    assert authenticate(session, token=alice_token).id == alice.id  # type: ignore[union-attr]
    found_bob = authenticate(session, token=bob_token)
    assert found_bob is not None and found_bob.id == bob.id and found_bob.role is Role.OPERATOR

    alice_id, secret = alice_token.split(".")
    for wrong in [
        f"{alice_id}.{secret[:-1]}x" if secret[-1] != "x" else f"{alice_id}.{secret[:-1]}y",
        f"{bob.id}.{secret}",  # alice's secret with bob's id
        secret,
        "",
        "999.abc",
        "1" * 40 + ".abc",
    ]:
        assert authenticate(session, token=wrong) is None, wrong


def test_tokens_are_stored_only_as_sha256(session: Session) -> None:
    labeller, token = create_labeller(session, name="alice")
    stored = session.scalars(select(Labeller.token_hash)).one()
    assert stored == hashlib.sha256(token.encode()).hexdigest()
    dump = session.execute(text("SELECT * FROM labellers")).all()
    assert token.split(".")[1] not in repr(dump)


def test_a_deactivated_labeller_is_refused(session: Session) -> None:
    labeller, token = create_labeller(session, name="alice")
    set_labeller_active(session, labeller_id=labeller.id, active=False)
    assert authenticate(session, token=token) is None
    set_labeller_active(session, labeller_id=labeller.id, active=True)
    assert authenticate(session, token=token) is not None


def test_names_are_unique(session: Session) -> None:
    create_labeller(session, name="alice")
    with pytest.raises(Conflict, match="alice"):
        create_labeller(session, name="alice")
    assert session.scalars(select(Labeller)).all()[0].name == "alice"


def test_a_labeller_is_renamed_promoted_and_revoked_in_one_call(session: Session) -> None:
    labeller, token = create_labeller(session, name="alice")
    create_labeller(session, name="bob")
    changed = update_labeller(
        session, labeller_id=labeller.id, name="alice2", role="operator", active=False
    )
    assert (changed.name, changed.role, changed.active) == ("alice2", Role.OPERATOR, False)
    assert authenticate(session, token=token) is None
    with pytest.raises(Conflict, match="bob"):
        update_labeller(session, labeller_id=labeller.id, name="bob")
    stored = session.get(Labeller, labeller.id)
    assert stored is not None and stored.name == "alice2"  # the refused rename changed nothing
    with pytest.raises(NotFound):
        update_labeller(session, labeller_id=labeller.id + 100, active=True)


def test_a_new_token_replaces_the_old_one(session: Session) -> None:
    labeller, old = create_labeller(session, name="alice")
    same, new = rotate_token(session, labeller_id=labeller.id)
    assert same.id == labeller.id and new != old
    assert authenticate(session, token=old) is None
    authenticated = authenticate(session, token=new)
    assert authenticated is not None and authenticated.id == labeller.id


def test_names_are_read_by_id(session: Session) -> None:
    alice, _ = create_labeller(session, name="alice")
    bob, _ = create_labeller(session, name="bob")
    assert labeller_names(session, ids={alice.id, bob.id, bob.id + 100}) == {
        alice.id: "alice", bob.id: "bob"}
    assert labeller_names(session, ids=set()) == {}
    assert not session.in_transaction()  # the read is ended: SQLite writers never wait on it
