"""The base of every typed metric: a pydantic model that is written as plain JSON data and read back.

A run's ``metrics.json`` is a tree of these (:class:`dem_graph.pipeline.metrics.RunMetrics`), so a
table column names a field (a renamed field fails a test, not a silent ``-``). Conventions:

- a field that is None was not measured (no ground truth, no DEM) and is left out of the JSON,
  except the fields a model lists in ``_keep_none`` (written as null);
- a number the JSON holds as null (NaN and infinities are written so) reads back as NaN.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, ClassVar

from pydantic import BaseModel, BeforeValidator, ConfigDict, model_serializer


def _nan_if_null(value: Any) -> Any:
    return math.nan if value is None else value


Number = Annotated[float, BeforeValidator(_nan_if_null)]
"""A float that JSON's null (how NaN is written) reads back as NaN."""


class MetricsModel(BaseModel):
    """A group of metrics: typed fields, unknown keys refused, None fields left out of the JSON."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)
    _keep_none: ClassVar[frozenset[str]] = frozenset()

    @model_serializer(mode="wrap")
    def _leave_out_none(self, handler) -> dict:
        data = handler(self)
        return {k: v for k, v in data.items() if v is not None or k in self._keep_none}

    def to_json_dict(self) -> dict:
        """The metrics as plain data for ``json``: nested dicts, lists, numbers and strings."""
        return self.model_dump(mode="python")


__all__ = ["MetricsModel", "Number"]
