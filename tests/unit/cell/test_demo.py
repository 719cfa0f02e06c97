"""``hrc cell demo``: the simulated robot and a human source together (here on a simulated clock)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from app.cell.clock import SimClock
from app.cell.demo import JointMove, run_demo, task_configurations
from app.cell.human import save_clip
from app.cell.operator_sim import SimulatedOperator
from app.cli import app as cli_app
from app.config import load_workcell
from app.planning.kinematics import QD_MAX, QDD_MAX, UR5e


def test_task_configurations_reach_the_stations() -> None:
    cell = load_workcell()
    configs = task_configurations(cell)
    kin = UR5e.from_workcell(cell)
    for station in cell.task_stations():
        T = kin.fk_tcp(configs[station.name][None])[0]
        np.testing.assert_allclose(T[:3, 3], station.xyz, atol=1e-6)
        np.testing.assert_allclose(T[:3, 2], [0.0, 0.0, -1.0], atol=1e-6)  # tool down


def test_joint_move_respects_the_limits() -> None:
    q0, q1 = np.zeros(6), np.array([1.0, -2.0, 0.5, 0.0, 3.0, -0.2])
    move = JointMove.timed(q0, q1, 1.0, qd_max=QD_MAX, qdd_max=QDD_MAX)
    t = np.linspace(move.t0, move.t_end, 2001)
    q = np.stack([move.sample(x)[0] for x in t])
    qd = np.stack([move.sample(x)[1] for x in t])
    assert np.all(np.abs(qd) <= QD_MAX + 1e-9)
    assert np.all(np.abs(np.diff(qd, axis=0) / np.diff(t)[:, None]) <= QDD_MAX + 1e-3)
    np.testing.assert_allclose(q[-1], q1)
    np.testing.assert_allclose(move.sample(0.0)[0], q0)


def test_demo_runs_robot_and_simulated_operator_together() -> None:
    report = run_demo(seconds=20.0, clock=SimClock(50.0), seed=1)
    assert report["frames"] == 600
    assert report["frame_rate_hz"] == pytest.approx(30.0)
    assert report["validation"]["accepted"] == 600 and report["validation"]["rejected"] == 0
    assert report["stale_events"] == 0
    assert report["control_loop"]["overruns"] == 0
    assert report["robot"]["blocks_placed"] >= 3
    assert report["robot"]["max_tracking_error_rad"] < 0.02
    assert report["operator"]["fetches"] >= 2  # the person took blocks the robot placed


def test_demo_replays_a_clip(tmp_path: Path) -> None:
    cell = load_workcell()
    op = SimulatedOperator(cell, seed=4)
    clip = save_clip(tmp_path / "clip.npz", [op.frame_at(k / 30) for k in range(45)])
    report = run_demo(seconds=4.0, source="replay", clip=clip, clock=SimClock())
    assert report["frames"] == 120  # looped: 1.5 s clip, 4 s run
    assert report["validation"]["accepted"] == 120
    with pytest.raises(ValueError, match="--clip"):
        run_demo(seconds=1.0, source="replay", clock=SimClock())


def test_cell_demo_command_prints_json() -> None:
    result = CliRunner().invoke(cli_app, ["cell", "demo", "--seconds", "0.5", "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    assert report["frames"] >= 1 and "validation" in report and "control_loop" in report
    bad = CliRunner().invoke(cli_app, ["cell", "demo", "--source", "replay"])
    assert bad.exit_code != 0
