"""docs/configuration.md documents every world config key with its current default; the shipped records
name no machine's folders."""

from __future__ import annotations

import dataclasses
import json
import re
import sqlite3
from contextlib import closing
from pathlib import Path

from gccp_envs.config import IntersectionConfig

ROOT = Path(__file__).resolve().parents[1]
CONFIGURATION = ROOT / "docs" / "configuration.md"
MACHINE_PATH = re.compile(r"(^|[^\w.])/(work|home|root|tmp|Users|mnt)/")
"""An absolute path into a machine's own folders, as a record would hold its run folder."""


def test_every_config_key_is_documented_with_its_default():
    text = CONFIGURATION.read_text()
    for field in dataclasses.fields(IntersectionConfig):
        value = getattr(IntersectionConfig(), field.name)
        shown = json.dumps(list(value) if isinstance(value, tuple) else value)
        assert f"| `{field.name}` | `{shown}` |" in text, field.name


def test_shipped_records_name_no_machine_folder():
    records = [
        path
        for folder in ("results", "pretrained")
        for path in sorted((ROOT / folder).rglob("*"))
        if path.suffix in {".json", ".yml", ".txt", ".csv", ".md"}
    ]
    assert records
    for path in records:
        assert not MACHINE_PATH.search(path.read_text()), path
    for study in sorted((ROOT / "results").rglob("*.db")):
        with closing(sqlite3.connect(study)) as db:
            values = [v for (v,) in db.execute("SELECT value_json FROM trial_user_attributes")]
        assert not any(MACHINE_PATH.search(v) for v in values), study
