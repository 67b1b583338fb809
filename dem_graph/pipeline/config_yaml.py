"""The run configuration written out for people: every field of :class:`~dem_graph.pipeline.config.RunConfig`
as YAML, each under a comment with its description and unit (``dem-graph config``).

The text reads back to the same configuration (:func:`~dem_graph.pipeline.config.run_config` with it as
``--config``): floats are written as Python's ``repr``, which YAML reads back to the same bits.
"""

from __future__ import annotations

import textwrap

import yaml
from pydantic import BaseModel

from dem_graph.pipeline.config import RunConfig

HEADER = """\
# dem_graph run configuration: every setting, each with its meaning and unit (`dem-graph config`).
# Give it back, whole or in part, with `dem-graph run DATASET --config FILE`. The layers, each over the one
# before: these defaults, the dataset's own run settings (KITTI brings a car's), this file, the flags.
# A value here that restates a default leaves a dataset's own setting in place (a file made by
# `dem-graph config` changes nothing on KITTI); a value that differs from the default wins over it.
"""


def _scalar_text(value) -> str:
    """One value as YAML on one line (lists in flow style)."""
    text = yaml.safe_dump(value, default_flow_style=True, width=10**9, sort_keys=False).strip()
    if text.endswith("\n..."):
        text = text[: -len("\n...")]
    return text.removesuffix("...").strip()


def _field_lines(model: BaseModel, indent: int) -> list[str]:
    pad = " " * indent
    lines: list[str] = []
    dumped = model.model_dump(mode="json")
    for name, info in type(model).model_fields.items():
        value = getattr(model, name)
        if info.description:
            text = " ".join(info.description.split())
            lines += [f"{pad}# {line}" for line in textwrap.wrap(text, width=max(40, 110 - indent))]
        if isinstance(value, BaseModel):
            lines.append(f"{pad}{name}:")
            lines += _field_lines(value, indent + 2)
        else:
            lines.append(f"{pad}{name}: {_scalar_text(dumped[name])}")
    return lines


def config_yaml(config: RunConfig | None = None) -> str:
    """``config`` (default: the defaults) as commented YAML: every field under its description."""
    config = RunConfig() if config is None else config
    return HEADER + "\n".join(_field_lines(config, 0)) + "\n"


__all__ = ["HEADER", "config_yaml"]
