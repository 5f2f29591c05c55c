"""The task names, defined once: every stage and config that lists tasks reads them here."""
from __future__ import annotations

from typing import Literal

TASKS = ("pick_place", "push", "pull", "move_to_aim")
Task = Literal[TASKS]  # the type of a config field holding one task name
TITLES = {"pick_place": "Pick & Place", "push": "Push", "pull": "Pull", "move_to_aim": "Move to Aim"}
