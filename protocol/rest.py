"""REST models (``/v1``): the one schema for the server's responses, the OpenAPI document and clients.

Pure pydantic; no I/O. Job states: ``queued`` -> ``running`` -> ``done`` | ``failed``; ``cancelled``
from ``queued`` or ``running``.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, Field

from .messages import InputKindIn

JobState = Literal["queued", "running", "done", "failed", "cancelled"]
FINAL_STATES: frozenset[str] = frozenset({"done", "failed", "cancelled"})
OutputFormat = Literal["glb", "npz", "fap"]
Engine = Literal["fp", "rbf", "shell"]

#: Media types of job results, by format.
RESULT_MEDIA_TYPES: dict[str, str] = {
    "glb": "model/gltf-binary",
    "npz": "application/octet-stream",
    "fap": "text/plain; charset=utf-8",
}

#: Media type of ``GET /v1/faces/{name}/topology`` (layout in ``protocol/TOPOLOGY.md``).
TOPOLOGY_MEDIA_TYPE = "application/vnd.facecast.topology"


class ErrorBody(BaseModel):
    """Every 4xx/5xx response: what was wrong and what to do."""

    error: str = Field(description="what was wrong and what to do about it")
    detail: str = Field(description="the same text as 'error' (FastAPI's usual field name)")
    status: int
    where: str | None = Field(None, description="file, line, field or parameter at fault")


class Health(BaseModel):
    status: Literal["ok"] = "ok"
    ready: bool = Field(description="default face loaded and backend probed")
    version: str
    uptime_seconds: float
    backend: str | None = Field(None, description="numpy | opencl (null until probed)")
    device: str | None = Field(None, description="OpenCL device(s) in use")
    face: dict[str, Any] | None = Field(None, description="default face: name, vertices")
    animator: bool = Field(
        False, description="the default face's animator is built (first session starts at once)"
    )
    warmup_seconds: float | None = Field(
        None, description="seconds the start-up warm-up took (null: still running)"
    )
    errors: dict[str, str] = Field(default_factory=dict)
    job_workers: int
    jobs: dict[str, int] = Field(default_factory=dict, description="jobs by state")


class FaceSummary(BaseModel):
    name: str
    builtin: bool
    default: bool = False
    vertices: int | None = Field(
        None,
        description="vertex count (approximate for a built-in face not loaded "
        "yet; null for a mesh not loaded yet)",
    )


class FaceList(BaseModel):
    faces: list[FaceSummary]
    default: str


class FaceInfo(BaseModel):
    name: str
    vertices: int
    triangles: int
    units: str
    mm_per_unit: float
    mesh_hash: str
    parts: dict[str, int] = Field(description="part name -> vertex count")
    rigid_groups: dict[str, int] = Field(description="rigid group -> vertex count")
    feature_points: int = Field(description="number of MPEG-4 feature points annotated")
    feature_point_ids: list[str]
    fapu: dict[str, float] | None = Field(
        None, description="MPEG-4 FAPU in mesh units (null if unmeasurable)"
    )
    bounds: list[list[float]] = Field(
        description="[[xmin,ymin,zmin],[xmax,ymax,zmax]] in mesh units"
    )
    topology_url: str


class JobOptions(BaseModel):
    """Form fields of ``POST /v1/jobs`` (besides the ``file`` part)."""

    face: str | None = Field(None, description="face name (GET /v1/faces); default: the server's")
    engine: Engine = "fp"
    format: OutputFormat = "glb"
    layout: str | None = Field(
        None,
        description="mocap marker layout: the layout file's JSON content, "
        "required for .c3d/.trc/.csv input (never a path); a job's status shows "
        "'uploaded' when it has one",
    )
    text: str | None = Field(
        None,
        max_length=10000,
        description="audio input only: its transcript (English); its phones are "
        "aligned to the audio; text that does not match the audio fails the job",
    )


class JobStatus(BaseModel):
    id: str
    status: JobState
    progress: float = Field(ge=0.0, le=1.0)
    error: str | None = None
    input_name: str = Field(description="the uploaded file's name (display only)")
    input_kind: InputKindIn | Literal["bml"] = Field(description="fap | audio | markers | bml")
    input_bytes: int
    options: JobOptions
    attempts: int = Field(description="times a worker started this job (restarts resume it)")
    created: float = Field(description="Unix time, seconds")
    started: float | None = None
    finished: float | None = None
    result_url: str | None = Field(None, description="GET this when status is done")
    result_bytes: int | None = None


class JobList(BaseModel):
    jobs: list[JobStatus]
