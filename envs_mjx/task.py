"""What a task declares beside its dynamics: its presets, its learning-curve budget and its contract's section.

Each env class carries one `Task` as its `task` attribute (docs/design.md, "A task in one place"); a subclass
inherits its parent's unless it sets its own. The command lines read it (`experiments.cli.task_preset`,
`experiments.paper.protocol.paper_epochs`); the learner never imports `envs_mjx`, so the presets are plain values:
config field names by group, which the run's config resolution lays over the defaults and checks.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping

Preset = Mapping[str, Mapping[str, Any]]  # {"run"|"train"|"network": {field: value}}


@dataclasses.dataclass(frozen=True)
class Task:
    """A task's own settings, each optional.

    Attributes:
      contract: where the task's contract is documented, e.g. "docs/tasks.md#planar_reach".
      presets: its overrides of the config defaults, for every agent (the options given override them).
      image_presets: laid over `presets` for an agent that learns from images (`Agent.uses_image`).
      paper_epochs: its learning-curve budget (paper Fig. 4), the same for every agent; None: not a task of the
        learning curves (`experiments.paper.curves --tasks` then needs `--epochs`).
    """

    contract: str = ""
    presets: Preset = dataclasses.field(default_factory=dict)
    image_presets: Preset = dataclasses.field(default_factory=dict)
    paper_epochs: int | None = None
