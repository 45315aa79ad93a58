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


# Magnitudes past which a description's value is a typo, by the field name's unit suffix: lengths within
# 100 m, angles within two turns, masses up to a tonne (the command guard trusts the joint limits: an inf or
# 1e308 limit would switch it off). Every float is finite (``allow_inf_nan=False``).
MAGNITUDE = {"_m": 100.0, "_rad": 4 * np.pi, "_kg": 1000.0}


class Part(BaseModel):
    """A part of a description: unknown keys refused, values frozen. ``_limits`` lists the part's limit
    pairs as ``(low, "<" or "<=", high)`` field names, checked on every axis of a vector."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    _limits: ClassVar[tuple[tuple[str, str, str], ...]] = ()

    @model_validator(mode="after")
    def _physical(self) -> Self:
        for name in type(self).model_fields:
            unit = next((u for u in MAGNITUDE if name.endswith(u) and "_per_" not in name), None)
            bound = MAGNITUDE.get(unit)
            value = getattr(self, name)
            if bound is None or value is None or isinstance(value, BaseModel | str | bool):
                continue
            try:
                size = float(np.max(np.abs(np.asarray(value, float))))
            except (TypeError, ValueError):
                continue
            if size > bound:
                raise ValueError(f"{name} {_shown(value)}: beyond {bound:g} (a typo? SI units: m, rad, kg)")
        return self

    @model_validator(mode="after")
    def _limits_in_order(self) -> Self:
        for low, order, high in self._limits:
            wrong, says = _OUT_OF_ORDER[order]
            a, b = getattr(self, low), getattr(self, high)
            if np.any(wrong(a, b)):
                axes = " on every axis" if np.ndim(a) else ""
                raise ValueError(f"{low} {_shown(a)} {says} {high} {_shown(b)}{axes}")
        return self
