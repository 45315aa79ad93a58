"""The base of a robot description's parts: a frozen pydantic model that refuses unknown keys and checks its
limit pairs, and the number types its fields use. Shared by ``models.robot`` and ``models.effects``."""

from __future__ import annotations

from typing import Annotated, ClassVar, Self

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

PositiveFloat = Annotated[float, Field(gt=0)]
NonNegFloat = Annotated[float, Field(ge=0)]

# how a limit pair may be the wrong way round, and what the error says then
_OUT_OF_ORDER = {"<": (np.greater_equal, "must be below"), "<=": (np.greater, "exceeds")}


def _shown(value: object) -> str:
    return str(value) if np.ndim(value) else f"({value})"


class Part(BaseModel):
    """A part of a description: unknown keys refused, values frozen. ``_limits`` lists the part's limit
    pairs as ``(low, "<" or "<=", high)`` field names, checked on every axis of a vector."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    _limits: ClassVar[tuple[tuple[str, str, str], ...]] = ()

    @model_validator(mode="after")
    def _limits_in_order(self) -> Self:
        for low, order, high in self._limits:
            wrong, says = _OUT_OF_ORDER[order]
            a, b = getattr(self, low), getattr(self, high)
            if np.any(wrong(a, b)):
                axes = " on every axis" if np.ndim(a) else ""
                raise ValueError(f"{low} {_shown(a)} {says} {high} {_shown(b)}{axes}")
        return self
