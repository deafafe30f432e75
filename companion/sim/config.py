"""Config section of the in-process simulator and the evaluation scenarios."""

from __future__ import annotations

from pydantic import Field

from companion.configbase import Section


class SimConfig(Section):
    seed: int = Field(0, ge=0)
