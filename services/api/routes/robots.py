"""GET /robots, /robots/{robot}/pose and /robots/{robot}/trajectory. They read only what the API holds and are
coroutines: they never wait."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, HTTPException, Path, Query

from schemas.messages import RESERVED_ROBOT_NAMES
from schemas.wire import NAME_PATTERN, NAME_RULE
from services.api import models
from services.api.robots import PoseSummary, RobotTracker, reduce_samples
from services.api.routes.common import ApiDep, PlainInteger, errors

router = APIRouter()

Robot = Annotated[
    str,
    Path(
        description=f"robot name, e.g. robot0 (GET /robots lists them): {NAME_RULE}",
        pattern=NAME_PATTERN,
    ),
]


def known_robot(robots: RobotTracker, robot: str) -> PoseSummary:
    """The robot's latest pose; 422 for a name no robot may have (reserved: schemas.messages.RESERVED_ROBOT_NAMES,
    which the path's pattern lets through), 404 naming the known robots when none has arrived."""
    if robot in RESERVED_ROBOT_NAMES:
        reserved = ", ".join(RESERVED_ROBOT_NAMES)
        raise HTTPException(422, f"{robot!r} is no robot name: it is reserved (reserved names: {reserved})")
    summary = robots.latest(robot)
    if summary is None:
        raise HTTPException(
            404, f"no pose of robot {robot!r} has arrived; robots: {', '.join(robots.robots()) or 'none'}"
        )
    return summary


@router.get("/robots", response_model=list[models.RobotSummary], tags=["robots"])
async def list_robots(api: ApiDep) -> list[models.RobotSummary]:
    """Robots whose poses the API has received."""
    robots = api.backend.robots
    processes = [p.split("/", 1) for p in sorted(api.backend.link.processes)]  # a copy: Zenoh's threads change it
    out = []
    for robot in robots.robots():
        s = robots.latest(robot)
        if s is None:  # forgotten since robots() listed it (services.api.robots: stray robots expire)
            continue
        out.append(
            models.RobotSummary(
                robot=robot,
                seq=s.seq,
                stamp=s.stamp,
                form=s.form,
                processes_alive=[process for owner, process in processes if owner == robot],
            )
        )
    return out


@router.get("/robots/{robot}/pose", response_model=models.Pose, tags=["robots"], responses=errors(404, 422))
async def pose(
    api: ApiDep,
    robot: Robot,
    max_samples: Annotated[
        int | None,
        Query(
            ge=1,
            description="return at most this many samples, reduced by systematic resampling "
            "(equal weights); default all",
        ),
        PlainInteger,
    ] = None,
) -> models.Pose:
    """The latest pose distribution: samples with weights, and their mean and covariance."""
    s = known_robot(api.backend.robots, robot)
    samples, weights = (
        (s.samples, s.weights) if max_samples is None else reduce_samples(s.samples, s.weights, max_samples)
    )
    return models.Pose(
        robot=robot,
        seq=s.seq,
        stamp=s.stamp,
        received=s.received,
        form=s.form,
        samples=samples.tolist(),
        weights=weights.tolist(),
        samples_total=len(s.weights),
        mean=s.mean.tolist(),
        covariance=s.cov.tolist(),
    )


@router.get("/robots/{robot}/trajectory", response_model=models.Trajectory, tags=["robots"], responses=errors(404, 422))
async def trajectory(api: ApiDep, robot: Robot) -> models.Trajectory:
    """The robot's mean poses since the API started, oldest first."""
    known_robot(api.backend.robots, robot)
    rows = api.backend.robots.trajectory(robot)
    return models.Trajectory(
        robot=robot,
        seq=rows[:, 0].astype(int).tolist(),
        stamp=rows[:, 1].tolist(),
        x=rows[:, 2].tolist(),
        y=rows[:, 3].tolist(),
        yaw=rows[:, 4].tolist(),
    )
