"""Operator endpoints for labellers: create (the token is shown once), list, change (revoke,
restore, role, name) and give a new token (the old one stops working)."""

from __future__ import annotations

from fastapi import APIRouter

from labelqueue import check_person_name, create_labeller, rotate_token, update_labeller
from server import services
from server.deps import OperatorDep, SessionDep, TokenCacheDep
from server.schemas import (
    LabellerCreate,
    LabellerCreated,
    LabellerId,
    LabellerOut,
    LabellerUpdate,
    errors,
)

router = APIRouter(prefix="/api/labellers", tags=["labellers"], responses=errors(401, 403))


@router.post(
    "", status_code=201, response_model=LabellerCreated, responses=errors(400, 409, 413, 422)
)
def new_labeller(body: LabellerCreate, session: SessionDep, _: OperatorDep) -> LabellerCreated:
    """A new labeller and its token (shown once); 409 for a name taken, or the scripted
    teacher's (`scripted-teacher`: workers make that labeller themselves)."""
    check_person_name(body.name)
    labeller, token = create_labeller(session, name=body.name, role=body.role)
    return LabellerCreated(id=labeller.id, name=labeller.name, role=labeller.role, token=token)


@router.get("", response_model=list[LabellerOut])
def list_labellers(session: SessionDep, _: OperatorDep) -> list[LabellerOut]:
    return [LabellerOut.model_validate(row) for row in services.list_labellers(session)]


@router.patch(
    "/{labeller_id}", response_model=LabellerOut, responses=errors(400, 404, 409, 413, 422)
)
def patch_labeller(
    labeller_id: LabellerId,
    body: LabellerUpdate,
    session: SessionDep,
    _: OperatorDep,
    cache: TokenCacheDep,
) -> LabellerOut:
    """Revoke (`active: false`) or restore a labeller, change its role or name. Leasing and
    answering stop at once everywhere; other reads stop at once in this server process, and
    within `SEPOA_AUTH_CACHE_SECONDS` in others (an operator-role labeller's: at once). 409
    for a name taken or the scripted teacher's, and for revoking or renaming the scripted
    teacher."""
    labeller = update_labeller(
        session, labeller_id=labeller_id, active=body.active, role=body.role, name=body.name
    )
    if cache is not None:
        cache.forget(labeller_id)
    return LabellerOut.model_validate(labeller)


@router.post(
    "/{labeller_id}/token", response_model=LabellerCreated, responses=errors(404, 409, 422)
)
def new_token(
    labeller_id: LabellerId, session: SessionDep, _: OperatorDep, cache: TokenCacheDep
) -> LabellerCreated:
    """A new bearer token for the labeller (shown this once); its old token stops working. 409
    for the scripted teacher, as whom no person answers."""
    labeller, token = rotate_token(session, labeller_id=labeller_id)
    if cache is not None:
        cache.forget(labeller_id)
    return LabellerCreated(id=labeller.id, name=labeller.name, role=labeller.role, token=token)
