"""Shared pydantic types: a strict base model and a 4x4 rigid transform field."""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import BaseModel, BeforeValidator, ConfigDict, PlainSerializer, ValidationError, WithJsonSchema

from dem_graph.geometry.se3 import check_pose


class StrictModel(BaseModel):
    """Base of every configuration model: unknown keys are errors, values are validated on assignment."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, frozen=False, arbitrary_types_allowed=True)


def _to_pose(value) -> np.ndarray:
    # the field name is attached by pydantic's error location; check_pose gives the problem
    try:
        return check_pose(value, "transform")
    except Exception as exc:  # turned into a pydantic validation error with the field's location
        raise ValueError(str(exc)) from None


Pose4x4 = Annotated[
    np.ndarray,
    BeforeValidator(_to_pose),
    PlainSerializer(lambda T: [[float(x) for x in row] for row in np.asarray(T)], return_type=list),
    WithJsonSchema({"type": "array", "items": {"type": "array", "items": {"type": "number"}}}),
]
"""A 4x4 rigid transform written as a nested list (row-major) in YAML."""


def format_validation_error(exc: ValidationError) -> str:
    """A pydantic validation error as one line: ``field.path: problem; ...``."""
    parts = []
    for err in exc.errors():
        loc = ".".join(str(x) for x in err["loc"]) or "(top level)"
        parts.append(f"{loc}: {err['msg']}")
    return "; ".join(parts)
