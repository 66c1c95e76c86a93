"""A model's held-out score beside the fast layer, stored in its file, and the rule the flight reads from it.

``cfknode train`` stores the per-axis share of what the layer leaves that the model removes too
(models/residual_check.py ``beyond_layer``); beside the layer an axis whose score is not above
``model_min_score`` flies no model (its coefficient held at 0), and a model with no such axis is not flown.
Files written before the score was stored fly every axis, as before.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from cfknode.app.config import load_config
from cfknode.app.mission import build_model_slot, model_not_flown
from cfknode.flight.adaptation import LoopAdaptation
from cfknode.flight.adaptation.composite import CoefficientSettings, ModelCoefficients
from cfknode.flight.mpc_problem import ResidualLinearisation
from cfknode.models.modelfile import ModelFile, ModelFileError, NetworkWeights, Normalisation, load_model, save_model
from cfknode.models.residual_check import SCORE_KEY, flown_axes, stored_score
from cfknode.models.residual_np import ResidualQueue


def small_model(extra: dict[str, object]) -> ModelFile:
    """One network with small weights (a plausible residual of a few cm/s^2) and the given metadata."""
    rng = np.random.default_rng(3)
    sizes = [6, 8, 3]
    layers = tuple((0.01 * rng.normal(size=(b, a)), 0.01 * rng.normal(size=b)) for a, b in zip(sizes[:-1], sizes[1:]))
    net = NetworkWeights(layers, Normalisation.identity())
    return ModelFile(hidden=(8,), activation="tanh", queue_size=1, networks=(net,), extra=extra)


def test_the_score_is_stored_and_read_back_and_older_files_still_load(tmp_path: Path) -> None:
    scored = load_model(save_model(tmp_path / "scored.safetensors", small_model({SCORE_KEY: [0.001, 0.03, -0.2]})))
    assert ResidualQueue.from_model_file(scored).beyond_layer.tolist() == [0.001, 0.03, -0.2]
    older = load_model(save_model(tmp_path / "older.safetensors", small_model({"config_knode": {}})))
    assert stored_score(older.extra) is None and ResidualQueue.from_model_file(older).beyond_layer is None
    for bad in ([0.1, 0.2], [0.1, "x", 0.2], "0.1", [0.1, True, 0.2]):
        path = save_model(tmp_path / "bad.safetensors", small_model({SCORE_KEY: bad}))
        with pytest.raises(ModelFileError, match=f"extra.{SCORE_KEY}"):
            load_model(path)


def test_an_axis_flies_the_model_only_where_its_score_is_above_the_threshold() -> None:
    assert flown_axes(None, 0.0) is None  # no score stored: every axis, as before
    assert flown_axes(np.array([0.0, 0.02, -0.1]), 0.0) == (False, True, False)
    assert flown_axes(np.array([0.007, 0.026, 0.081]), 0.01) == (False, True, True)


def test_an_axis_that_flies_no_model_is_the_layers_alone() -> None:
    coeffs = ModelCoefficients(CoefficientSettings((0.0, 1.5), 4.0, 0.05, 1.0), 400.0, flown=(False, True, True))
    assert coeffs.a.tolist() == [0.0, 1.0, 1.0]
    r = np.array([0.4, -0.3, 2.0])
    for _ in range(400):  # the fit runs, the mean moves; x stays out
        shift = coeffs.tick(r + 0.1 * np.random.default_rng(0).normal(size=3), np.array([0.05, 0.0, 0.0]),
                            np.full(3, 10.0), 1.0 / 400.0, learn=True)
        assert shift[0] == 0.0
    assert coeffs.a[0] == 0.0 and coeffs.prediction(r)[0] == 0.0 and coeffs.predictions(r[None, :])[0, 0] == 0.0
    lin = ResidualLinearisation(np.tile(r, (3, 1)), np.ones((3, 3, 6)), np.ones((3, 3, 3)))
    offset = np.array([0.2, 0.1, 0.05])
    for acts in (True, False):
        flown = coeffs.linearisation(lin, offset, vertical_acts=acts)
        assert np.all(flown.c[:, 0] == 0.2) and not flown.jx[:, 0].any() and not flown.ju[:, 0].any()
        assert flown.c[0, 1] != 0.1  # y flies the model
    coeffs.restart(np.tile(r, (5, 1)))  # a model without a score: every axis again
    assert coeffs.a.tolist() == [1.0, 1.0, 1.0]


def test_the_loop_reads_the_models_axes_from_its_score() -> None:
    cfg = load_config(overrides={"controller.adaptation": "dob",
                                 "controller.adaptation_settings.model_min_score": 0.01})
    adapt = LoopAdaptation(cfg.controller, cfg.vehicle, ground_z=0.0)
    scored = SimpleNamespace(version=1, model=SimpleNamespace(beyond_layer=np.array([0.007, 0.026, 0.081])))
    older = SimpleNamespace(version=1, model=SimpleNamespace())
    assert adapt._flown(scored) == (False, True, True) and adapt._flown(older) == (True, True, True)
    adapt._use_coefficients(scored)
    assert adapt.coefficients is not None and adapt.coefficients.a.tolist() == [0.0, 1.0, 1.0]
    assert adapt.summary()["adaptation_model_axes"] == "yz"


def test_a_model_with_no_positive_score_is_not_flown_beside_the_layer(tmp_path: Path, caplog) -> None:
    path = save_model(tmp_path / "m.safetensors", small_model({SCORE_KEY: [0.0, -0.05, -1.2]}))
    cfg = load_config(overrides={"controller.model": str(path), "controller.adaptation": "dob"})
    notes: list[str] = []
    with caplog.at_level(logging.WARNING):
        assert build_model_slot(cfg, notes) is None
    assert len(notes) == 1 and "\n" not in notes[0] and notes[0].startswith("model not flown")
    assert notes[0] in caplog.text
    # Without the layer the score says nothing (it is the share beyond the layer): the model flies.
    alone = dataclasses.replace(cfg, controller=dataclasses.replace(cfg.controller, adaptation="none"))
    assert build_model_slot(alone) is not None
    # One positive axis, or no score stored: flown.
    assert model_not_flown(cfg, np.array([0.0, 0.02, -1.0])) is None and model_not_flown(cfg, None) is None
    older = save_model(tmp_path / "older.safetensors", small_model({}))
    assert build_model_slot(load_config(overrides={"controller.model": str(older),
                                                   "controller.adaptation": "dob"})) is not None
