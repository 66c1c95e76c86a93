"""Each setting declared once: the field in its settings dataclass, the packaged YAML and the bounds agree."""

from __future__ import annotations

import json
from pathlib import Path

from cfknode.app.config import load_config

DATA = Path(__file__).parent / "data"


def test_the_loaded_default_config_is_unchanged():
    """Every flown number stays: the packaged defaults load to the recorded Config, field for field."""
    recorded = json.loads((DATA / "default_config.json").read_text())
    assert json.loads(json.dumps(load_config().to_dict())) == recorded
