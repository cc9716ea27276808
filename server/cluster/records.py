"""What a cluster keeps in Redis and answers on ``GET /v1/cluster``, as JSON models."""

from __future__ import annotations

import time
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from ...protocol.messages import SessionInfo, Stats
from ..live.session import SessionSpec


class NodeRecord(BaseModel):
    """One node, as it announces itself."""

    id: str
    url: str  #: where it serves (its bind address and port)
    host: str  #: machine name
    pid: int
    started: float = Field(default_factory=time.time)  #: Unix time
    version: str = ""


class SessionRecord(BaseModel):
    """A live session as every node needs it to authorise its peers and to take it over."""

    model_config = ConfigDict(extra="ignore")

    id: str
    face: str
    input: Literal["fap", "audio", "markers"]
    fps: float
    engine: str
    max_viewers: int
    producer_token: str
    viewer_token: str
    created: float
    tolerance: float
    vertex_count: int = 0

    @classmethod
    def of(cls, spec: SessionSpec, vertex_count: int = 0) -> SessionRecord:
        return cls(
            vertex_count=vertex_count,
            id=spec.id,
            face=spec.face,
            input=spec.input,
            fps=spec.fps,
            engine=spec.engine,
            max_viewers=spec.max_viewers,
            producer_token=spec.producer_token,
            viewer_token=spec.viewer_token,
            created=spec.created,
            tolerance=spec.tolerance,
        )

    def spec(self) -> SessionSpec:
        return SessionSpec(**self.model_dump(exclude={"vertex_count"}))

    def info(self, stats: Stats) -> SessionInfo:
        """``GET /v1/sessions/{id}`` of this session, with its owner's last ``stats``."""
        return SessionInfo(
            id=self.id,
            face=self.face,
            input=self.input,
            fps=self.fps,
            engine=self.engine,
            created=self.created,
            vertex_count=self.vertex_count,
            max_viewers=self.max_viewers,
            stats=stats,
        )


class NodeView(BaseModel):
    """A node on ``GET /v1/cluster``: its record, the sessions it owns, whether it answered."""

    id: str
    url: str
    host: str
    pid: int
    started: float
    version: str = ""
    sessions: list[str] = Field(default_factory=list)
    is_self: bool = Field(default=False, serialization_alias="self")


class ClusterView(BaseModel):
    """``GET /v1/cluster``: the nodes (one, itself, without a broker), the broker's state."""

    self_id: str = Field(serialization_alias="self")
    broker: Literal["none", "up", "down"]
    nodes: list[NodeView]
    orphans: list[str] = Field(default_factory=list)  #: sessions whose lease no node holds now
