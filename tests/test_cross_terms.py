"""Command maps with a cross term (``--cross-terms``): a differential drive whose wheels differ turns while
commanded straight, so its turn map reads the forward command too. The term goes last in the turn map's vector;
model.json keeps ``coefficients`` a power series and holds it under ``cross``."""
from __future__ import annotations

import json

import numpy as np
import pytest

import casm_graph as cg
from casm_graph.cli import main
from casm_graph.io.log import LogError
from casm_graph.models.command_model import CommandModel, for_commands
from casm_graph.models.model import Model
from casm_graph.models.validate import Where
from casm_graph.sim.floor import FloorConfig
from casm_graph.sim.floor import simulate as simulate_floor
from casm_graph.sim.protocols import write_log


def coupled(rng) -> CommandModel:
    u = rng.uniform(-0.5, 0.5, size=(200, 2))
    return for_commands(u, 2, 1, cross=True).with_params(np.array([0.01, 0.45, -0.02, 0.02, 0.9, 0.25]),
                                                         std=np.full(6, 0.01))


def test_the_turn_map_reads_the_forward_command_through_its_last_coefficient():
    rng = np.random.default_rng(0)
    cm = coupled(rng)
    assert cm.sizes == (3, 0, 3) and cm.cross and cm.cross_coefficient("w") is not None
    u = rng.uniform(-0.5, 0.5, size=(50, 2))
    s = np.asarray(cm.scale)
    x = u / s
    speed = 0.01 + 0.45 * x[:, 0] - 0.02 * x[:, 0] ** 2
    turn = 0.02 + 0.9 * x[:, 1] + 0.25 * x[:, 0]
    np.testing.assert_allclose(cm.velocities(u), np.column_stack([speed, np.zeros(50), turn]))
    assert cm.coefficients("w")[0].tolist() == [0.02, 0.9] and cm.cross_coefficient("w")[0] == 0.25
    assert cm.cross_coefficient("v") is None
    plain = for_commands(u, 2, 1, cross=True, gain=1.0)
    np.testing.assert_allclose(plain.velocities(u)[:, [0, 2]], u)           # the nominal map: velocity = command
    assert for_commands(rng.normal(size=(9, 3)), cross=True).cross is False   # omnidirectional: no cross terms


def test_the_cross_term_round_trips_through_model_json_and_older_readers_see_the_power_series():
    cm = coupled(np.random.default_rng(1))
    data = json.loads(json.dumps(cm.to_json()))
    assert data["coefficients"] == {"v": [0.01, 0.45, -0.02], "w": [0.02, 0.9]}
    assert data["cross"] == {"w": {"v": 0.25}} and data["cross_std"] == {"w": {"v": 0.01}}
    back = CommandModel.read(Where("model.json"), data)
    assert back.cross and np.array_equal(back.params, cm.params) and np.array_equal(back.w_std, cm.w_std)
    units = CommandModel.coefficients_in_units(data)
    assert units["w_from_v"][0] == pytest.approx([0.25 / cm.scale[0]])
    assert "w_from_v" in CommandModel.brief(data) and ("w from v", "command_map") == CommandModel.figures(data)[-1][:2]
    older = {k: v for k, v in data.items() if k not in ("cross", "cross_std")}
    assert not CommandModel.from_json(older).cross


@pytest.mark.parametrize("cross, message", [
    ({"v": {"w": 0.1}}, "the turn map's in v"),
    ({"w": {"w": 0.2}}, r"action_model.cross.w.v"),
    ({"w": {"v": "a"}}, r"action_model.cross.w.v"),
    ({"w": 0.2}, r"action_model.cross.w"),
])
def test_a_malformed_cross_entry_fails_in_one_line(cross, message):
    data = coupled(np.random.default_rng(2)).to_json()
    data["cross"] = cross
    with pytest.raises(LogError, match=message):
        CommandModel.read(Where("model.json"), data)


def test_a_model_json_with_cross_terms_loads_as_a_model(tmp_path):
    m = Model(action_ids=np.array([], int), velocities=np.zeros((0, 3)), reading_poly=np.array([0.0, 1.0]),
              reading_sigma=1.0, bearing_sigma=0.05, motion_noise=np.array([0.01, 0.01, 0.02]),
              command=coupled(np.random.default_rng(3)))
    m.save(tmp_path / "model.json")
    back = Model.load(tmp_path / "model.json")
    assert back.command.cross and np.array_equal(back.command.params, m.command.params)


@pytest.fixture(scope="module")
def floor():
    log, truth = simulate_floor(FloorConfig(minutes=3, seed=1))
    return log, truth


def test_a_floor_whose_turn_does_not_follow_the_speed_keeps_the_plain_maps(floor):
    """The project's floor maps each command alone: the auto choice tries the term and leaves it out (its Wald
    statistic far below BIC's bar), and the calibration is the one without the choice, to the bit."""
    log, _ = floor
    auto, off = cg.calibrate(log, seed=0), cg.calibrate(log, seed=0, cross_terms=False)
    ct = auto.model.fit["cross_term"]
    assert not ct["kept"] and ct["delta_bic"] > 0 and not auto.model.command.cross
    assert np.array_equal(auto.model.command.params, off.model.command.params)
    assert np.array_equal(auto.trajectory["x"], off.trajectory["x"]) and "cross_term" not in off.model.fit
    assert "not kept" in auto.summary()
    assert auto.model_json["fit"]["options"]["cross_terms"] == "auto"


def test_a_bad_cross_terms_option_is_one_line():
    with pytest.raises(LogError, match="cross_terms must be"):
        cg.calibrate(simulate_floor(FloorConfig(minutes=0.5, seed=0))[0], cross_terms="yes")


def test_the_command_line_records_its_choice(floor, tmp_path, capsys):
    """``--cross-terms on`` fits the term from the start and model.json holds it; the printout says what the
    auto choice did."""
    log, truth = floor
    write_log(log, tmp_path / "log", truth)
    assert main(["calibrate", str(tmp_path / "log"), "--out", str(tmp_path / "on"), "--cross-terms", "on",
                 "--quiet"]) == 0
    m = json.loads((tmp_path / "on" / "model.json").read_text())
    assert m["fit"]["options"]["cross_terms"] is True and set(m["action_model"]["cross"]) == {"w"}
    assert "cross_term" not in m["fit"]
    assert main(["calibrate", str(tmp_path / "log"), "--out", str(tmp_path / "auto"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "turn rate per forward speed (unequal wheels):" in out and ", not kept (delta BIC" in out
