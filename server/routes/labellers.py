"""Operator endpoints for labellers: create (the token is shown once) and list."""

from __future__ import annotations

from fastapi import APIRouter

from labelqueue import create_labeller
from server import services
from server.deps import OperatorDep, SessionDep
from server.schemas import LabellerCreate, LabellerCreated, LabellerOut

router = APIRouter(prefix="/api/labellers", tags=["labellers"])


@router.post("", status_code=201, response_model=LabellerCreated)
def new_labeller(body: LabellerCreate, session: SessionDep, _: OperatorDep) -> LabellerCreated:
    labeller, token = create_labeller(session, name=body.name, role=body.role)
    return LabellerCreated(id=labeller.id, name=labeller.name, role=labeller.role, token=token)


@router.get("", response_model=list[LabellerOut])
def list_labellers(session: SessionDep, _: OperatorDep) -> list[LabellerOut]:
    return [LabellerOut.model_validate(row) for row in services.list_labellers(session)]
