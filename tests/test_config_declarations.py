"""Each setting declared once: the field in its settings dataclass, the packaged YAML and the bounds agree.

A key's default, unit, bounds and meaning are declared on its field (``cfknode.kernel.setting``);
the packaged YAML files hold the values of fields without a default, and the comment on each key's
line is the declared meaning. These tests fail when a second place disagrees with the declaration.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from cfknode.app.config import PACKAGED, _RULES, load_config
from cfknode.app.config_bounds import BOUNDS, Bound
from cfknode.app.config_docs import configuration_doc, packaged_keys, packaged_text, with_declared_comments
from cfknode.app.declarations import declared, leaf_keys
from cfknode.flight.adaptation.settings import AdaptationSettings
from cfknode.flight.settings import AdaptationTuning

DATA = Path(__file__).parent / "data"
ROOT = Path(__file__).parent.parent
USER_FILE, TUNING_FILE = PACKAGED
MAX_USER_KEYS = 60


def _get(obj, dotted):
    for part in dotted.split("."):
        obj = getattr(obj, part)
    return obj


def test_the_loaded_default_config_is_unchanged():
    """Every flown number stays: the packaged defaults load to the recorded Config, field for field."""
    recorded = json.loads((DATA / "default_config.json").read_text())
    assert json.loads(json.dumps(load_config().to_dict())) == recorded


def test_every_packaged_key_is_one_field_and_every_field_one_packaged_key():
    user, tuning = packaged_keys(USER_FILE), packaged_keys(TUNING_FILE)
    assert len(user) == len(set(user)) and len(tuning) == len(set(tuning))
    assert sorted(set(user) & set(tuning)) == []  # each key in one file only
    assert sorted(user + tuning) == sorted(leaf_keys())


def test_the_user_file_holds_at_most_60_keys():
    assert len(packaged_keys(USER_FILE)) <= MAX_USER_KEYS


def test_a_field_default_is_the_packaged_value():
    cfg = load_config()
    for d in declared():
        if not d.record and d.default is not dataclasses.MISSING:
            assert _get(cfg, d.key) == d.default, d.key


def test_the_layers_settings_mirror_the_declared_tuning_without_a_second_default():
    """``AdaptationSettings`` is filled from ``controller.adaptation_settings``: the same names, no defaults of its own."""
    mirrored = {f.name for f in dataclasses.fields(AdaptationSettings)} - {"mode"}
    assert mirrored == {f.name for f in dataclasses.fields(AdaptationTuning)}
    for f in dataclasses.fields(AdaptationSettings):
        assert f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING, f.name


def test_bounds_are_the_declared_ones():
    expected = {d.key: Bound(*d.bounds[:2], d.unit, *d.bounds[2:]) for d in declared() if d.bounds is not None}
    assert BOUNDS == expected


@pytest.mark.parametrize("key, ok, what", _RULES, ids=[r[0] for r in _RULES])
def test_a_rule_beside_a_bound_never_refuses_a_value_the_bound_admits(key, ok, what):
    """``_RULES`` (config.py) hold what a range cannot say; where a key also has a range, the rule admits its ends."""
    bound = BOUNDS.get(key)
    value = _get(load_config(), key)
    if bound is None or isinstance(value, (tuple, list)) or value is None:
        pytest.skip("no scalar bound to compare")
    ends = [e for e, open_ in ((bound.low, bound.low_open), (bound.high, bound.high_open)) if not open_]
    for v in ends + [(bound.low + bound.high) / 2]:  # a rule may cut a gap (0 or 2..50 Hz), not an end
        assert ok(int(v) if isinstance(value, int) and float(v).is_integer() else v), (key, v, what)


def test_every_key_has_a_one_line_meaning():
    for d in declared():
        assert d.doc and "\n" not in d.doc and len(d.doc) <= 120, d.key
        assert d.doc.strip() not in ("", d.unit), f"{d.key}: the meaning only repeats the unit"


@pytest.mark.parametrize("name", PACKAGED)
def test_a_packaged_yaml_comment_is_the_declared_meaning(name):
    text = packaged_text(name)
    assert text == with_declared_comments(text), "run: python -m cfknode.app.config_docs --yaml"


def test_a_wrong_comment_is_found():
    text = packaged_text(USER_FILE).replace("# gravitational acceleration", "# gravity on the Moon")
    assert "gravity on the Moon" in text and with_declared_comments(text) != text


def test_the_committed_configuration_doc_is_the_generated_one():
    committed = (ROOT / "docs" / "configuration.md").read_text()
    assert committed == configuration_doc(), "run: python -m cfknode.app.config_docs > docs/configuration.md"
