"""configs/*.yaml: they load as PaConfig, and default.yaml documents every key with a comment."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from pa_cli.config import PaConfig, load_config

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


@pytest.mark.parametrize("name", ["default", "indoor", "outdoor"])
def test_config_loads(name):
    config = load_config(CONFIGS / f"{name}.yaml")
    assert isinstance(config, PaConfig)


def test_default_yaml_is_the_defaults():
    raw = yaml.safe_load((CONFIGS / "default.yaml").read_text())
    assert raw == PaConfig().model_dump(mode="json")


def test_every_key_documented_in_default_yaml():
    lines = (CONFIGS / "default.yaml").read_text().splitlines()
    section = None
    documented: set[tuple[str, str]] = set()
    for line in lines:
        m = re.match(r"^(\w+):\s*#\s*\S", line)
        if m:
            section = m.group(1)
            continue
        m = re.match(r"^  (\w+):\s*\S+\s+#\s*(.+)$", line)
        if m and section:
            documented.add((section, m.group(1)))
    expected = {(s, k) for s, f in PaConfig.model_fields.items() for k in f.annotation.model_fields}
    assert expected - documented == set(), "keys without a comment in configs/default.yaml"
    assert documented - expected == set(), "keys in configs/default.yaml that PaConfig does not have"
