"""The reference scenario set: synthetic and recorded people at the operator's side, reaching in."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.config import WorkCell, load_workcell
from app.planning.scenarios import _reaches_in, _through_table, recorded_forecasts, synthetic_forecast
from app.prediction.skeleton import JOINT_INDEX


@pytest.fixture(scope="module")
def cell() -> WorkCell:
    return load_workcell()


def _in_operator_area(joints: np.ndarray, cell: WorkCell) -> bool:
    pelvis = joints[0, JOINT_INDEX["pelvis"], :2]
    lo = np.asarray(cell.operator.center_xy) - np.asarray(cell.operator.size_xy) / 2
    hi = np.asarray(cell.operator.center_xy) + np.asarray(cell.operator.size_xy) / 2
    return bool(np.all(pelvis >= lo - 1e-9) and np.all(pelvis <= hi + 1e-9))


def test_synthetic_people_stand_at_the_operator_side_and_reach_in(cell: WorkCell) -> None:
    reaching = 0
    for seed in range(20):
        fc = synthetic_forecast(cell, seed=seed)
        assert _in_operator_area(fc.joints, cell)
        assert not _through_table(fc.joints, cell)
        reaching += _reaches_in(fc.joints, cell)
    assert reaching >= 15
    still = synthetic_forecast(cell, seed=1, reach=False)
    np.testing.assert_allclose(still.joints, still.joints[:1].repeat(still.joints.shape[0], axis=0))


def test_a_hand_below_the_table_top_is_seen(cell: WorkCell) -> None:
    fc = synthetic_forecast(cell, seed=3, reach=False)
    joints = fc.joints.copy()
    joints[5, JOINT_INDEX["r_hand"]] = [0.6, 0.0, -0.05]  # over the table, 5 cm below its top
    assert _through_table(joints, cell)
    joints[5, JOINT_INDEX["r_hand"]] = [0.6, 0.0, 0.10]
    assert not _through_table(joints, cell)


def test_recorded_people_are_placed_realistically_and_reproducibly(cell: WorkCell, cmu_dir: Path) -> None:
    got = recorded_forecasts(cell, cmu_dir, n=8, seed=8)
    assert len(got) == 8
    sources = {src for _, src in got}
    assert all(src.startswith("recorded:") for src in sources)
    for fc, _ in got:
        assert _in_operator_area(fc.joints, cell)
        assert _reaches_in(fc.joints, cell)
        assert not _through_table(fc.joints, cell)
        assert fc.joints.shape[0] == fc.times.shape[0] == 31
    again = recorded_forecasts(cell, cmu_dir, n=8, seed=8)
    for (a, sa), (b, sb) in zip(got, again, strict=True):
        assert sa == sb
        np.testing.assert_array_equal(a.joints, b.joints)
