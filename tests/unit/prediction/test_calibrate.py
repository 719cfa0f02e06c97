from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from app.cell.recording import simulated_operator_sequences
from app.cli import app
from app.config import Settings
from app.prediction.calibrate import calibrate_quantiles, write_quantiles
from app.prediction.predictor import MotionPredictor, load_quantiles
from app.prediction.skeleton import JOINT_INDEX, NUM_JOINTS


@pytest.fixture(scope="module")
def sequences() -> list[np.ndarray]:
    cell = Settings().load_workcell()
    return simulated_operator_sequences(
        cell, participants=2, duration_s=20.0, seed=5, block_every_s=(4.0, 6.0)
    )


def test_simulated_sequences_are_deterministic_and_include_fetches(sequences: list[np.ndarray]) -> None:
    assert [s.shape for s in sequences] == [(600, NUM_JOINTS, 3)] * 2
    cell = Settings().load_workcell()
    again = simulated_operator_sequences(
        cell, participants=1, duration_s=20.0, seed=5, block_every_s=(4.0, 6.0)
    )
    np.testing.assert_array_equal(again[0], sequences[0])
    # a fetch reaches past the work spot toward the drop stations (the robot side is -x)
    hands = sequences[0][:, [JOINT_INDEX["l_hand"], JOINT_INDEX["r_hand"]]]
    assert hands[..., 0].min() < cell.operator.work_spot[0] - 0.25


def test_calibrated_quantiles_grow_with_the_horizon_and_feed_the_predictor(
    sequences: list[np.ndarray], tmp_path: Path
) -> None:
    predictor = MotionPredictor(kind="graphmixer")
    result = calibrate_quantiles(sequences, predictor, stride=4)
    assert set(result["kinds"]) == {"graphmixer", "constant_velocity", "zero_velocity"}
    n = (600 - 40) // 4 + 1
    assert result["windows"] == 2 * n
    for entry in result["kinds"].values():
        p50, p95 = np.asarray(entry["p50"]), np.asarray(entry["p95"])
        assert p50.shape == (31,) and p50[0] == 0.0
        assert np.all(p95 >= p50) and p50[-1] > p50[1]
    path = write_quantiles(tmp_path / "q.json", result, fps=30.0, horizon=30, source="test")
    doc = load_quantiles(path)
    assert doc["source"] == "test" and doc["windows"] == result["windows"]
    calibrated = MotionPredictor(kind="graphmixer", quantiles=path, margin_quantile="p50", growth_mps=0.0)
    np.testing.assert_allclose(calibrated.margins_for("graphmixer"), result["kinds"]["graphmixer"]["p50"])


def test_bad_calibration_input_is_rejected(sequences: list[np.ndarray]) -> None:
    predictor = MotionPredictor(kind="graphmixer")
    with pytest.raises(ValueError, match="shorter than 40 frames"):
        calibrate_quantiles([sequences[0][:30]], predictor)
    bad = sequences[0].copy()
    bad[3, 2, 1] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        calibrate_quantiles([bad], predictor)
    with pytest.raises(ValueError, match="shape"):
        calibrate_quantiles([sequences[0][:, :5]], predictor)
    with pytest.raises(ValueError, match="stride"):
        calibrate_quantiles(sequences, predictor, stride=0)


def test_calibrate_command_writes_a_file_the_runtime_reads(tmp_path: Path) -> None:
    out = tmp_path / "cell.quantiles.json"
    res = CliRunner().invoke(
        app,
        ["hmp", "calibrate", "--out", str(out), "--sim-participants", "1", "--duration", "10", "--json"],
    )
    assert res.exit_code == 0, res.output
    summary = json.loads(res.output)
    assert summary["out"] == str(out) and summary["windows"] > 0
    assert load_quantiles(out)["kinds"]["graphmixer"]["p50"][0] == 0.0
    res = CliRunner().invoke(app, ["hmp", "calibrate", "--out", str(out), "--sim-participants", "0"])
    assert res.exit_code != 0 and "--clips" in res.output
