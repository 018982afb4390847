"""Adaptation of a policy version to a diagnosed site: POST starts one on a finished diagnosis
run (server.analysis.adaptation; the new version then appears under Policies with its twin evaluation on
the site's fitted profile, ready to promote); GET lists and reads runs."""

from __future__ import annotations

from typing import Literal

from fastapi import APIRouter
from pydantic import BaseModel, Field

from server.api.deps import AdaptationRunsDep, AdminDep, ViewerDep
from server.api.report_schemas import AdaptationRunOut
from server.api.responses import errors
from server.errors import found

router = APIRouter(tags=["adaptation"])


AdaptDep = AdaptationRunsDep


class AdaptCreate(BaseModel):
    mode: Literal["2d", "3d"]
    base_version: str | None = Field(None, max_length=128, description="default: the version the diagnosed machine runs")
    throws: int = Field(20, ge=2, le=200, description="twin throws per target distance and round")
    rounds: int = Field(2, ge=1, le=4)


@router.post("/api/diagnosis/runs/{run_id}/adapt", status_code=202, response_model=AdaptationRunOut,
             responses=errors((404, "no such diagnosis"), (409, "not done, busy or no base file")))
def create_adaptation(run_id: str, body: AdaptCreate, runs: AdaptDep, user: AdminDep) -> dict:
    """Adapt the machine's policy to the diagnosis' fitted profile (aim correction in the CPU
    twin, in the background); its progress comes as ``job`` events on /api/live."""
    return runs.start(run_id, body.mode, user.username, body.base_version, body.throws, body.rounds)


@router.get("/api/adaptations", response_model=list[AdaptationRunOut])
def list_adaptations(runs: AdaptDep, _user: ViewerDep) -> list[dict]:
    """Adaptation runs, newest first."""
    return runs.list()


@router.get("/api/adaptations/{adapt_id}", response_model=AdaptationRunOut, responses=errors((404, "no such run")))
def get_adaptation(adapt_id: str, runs: AdaptDep, _user: ViewerDep) -> dict:
    """Status, progress lines and (when done) the new policy version's id and name."""
    return found(runs.get(adapt_id), f"no adaptation run {adapt_id}")
