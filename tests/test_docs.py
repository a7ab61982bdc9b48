"""docs/configuration.md documents every world config key with its current default."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from gccp_envs.config import IntersectionConfig

CONFIGURATION = Path(__file__).resolve().parents[1] / "docs" / "configuration.md"


def test_every_config_key_is_documented_with_its_default():
    text = CONFIGURATION.read_text()
    for field in dataclasses.fields(IntersectionConfig):
        value = getattr(IntersectionConfig(), field.name)
        shown = json.dumps(list(value) if isinstance(value, tuple) else value)
        assert f"| `{field.name}` | `{shown}` |" in text, field.name
