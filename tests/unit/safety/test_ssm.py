from __future__ import annotations

import math

import numpy as np
import pytest

from app.safety.ssm import (
    SSMParams,
    forecast_clearance,
    max_safe_speed,
    protective_separation,
    speed_scale,
)
from app.safety.stopping import StoppingModel


def test_protective_separation_matches_iso_ts_15066_terms() -> None:
    p = SSMParams(
        v_human_mps=1.6, t_reaction_s=0.1, t_stop_s=0.3, intrusion_m=0.05, z_human_m=0.04, z_robot_m=0.01
    )
    v_r = 0.8
    s_h = 1.6 * (0.1 + 0.3)
    s_r = 0.8 * 0.1
    s_s = 0.8 * 0.3 / 2
    assert protective_separation(v_r, p) == pytest.approx(s_h + s_r + s_s + 0.05 + 0.04 + 0.01)
    # a measured human speed replaces the default one
    assert protective_separation(v_r, p, v_human_mps=0.5) == pytest.approx(0.5 * 0.4 + s_r + s_s + 0.1)


def test_defaults_are_the_documented_ones() -> None:
    p = SSMParams()
    assert p.v_human_mps == 1.6
    assert protective_separation(0.0, p) == pytest.approx(1.6 * (p.t_reaction_s + p.t_stop_s) + p.constant_m)


def test_max_safe_speed_inverts_protective_separation() -> None:
    p = SSMParams()
    for v in (0.0, 0.1, 0.5, 1.2):
        d = protective_separation(v, p)
        assert max_safe_speed(d, p) == pytest.approx(v)
    # inside S_p(0) the robot must stand still
    assert max_safe_speed(protective_separation(0.0, p) - 0.01, p) == 0.0
    arr = max_safe_speed(np.array([0.0, 10.0]), p)
    assert arr.shape == (2,) and arr[0] == 0.0 and arr[1] > 1.0


def test_speed_scale_is_a_fraction_and_monotone() -> None:
    p = SSMParams()
    d = np.linspace(0.0, 3.0, 61)
    s = np.array([speed_scale(x, 1.0, p) for x in d])
    assert np.all((s >= 0.0) & (s <= 1.0))
    assert np.all(np.diff(s) >= 0.0)
    assert s[0] == 0.0 and s[-1] == 1.0
    assert speed_scale(math.inf, 1.0, p) == 1.0
    assert speed_scale(0.0, 0.0, p) == 0.0  # standing still inside S_p(0): no motion allowed
    # the scaled speed keeps S_p within the separation
    d0 = protective_separation(0.0, p) + 0.1
    scale = speed_scale(d0, 2.0, p)
    assert protective_separation(2.0 * scale, p) == pytest.approx(d0)


def test_forecast_clearance_uses_the_larger_of_sensing_and_forecast_error() -> None:
    p = SSMParams(z_human_m=0.05)
    base = p.intrusion_m + p.z_robot_m
    assert forecast_clearance(0.0, 0.01, p, w_top_radps=0.0) == pytest.approx(base + 0.05)
    assert forecast_clearance(0.0, 0.2, p, w_top_radps=0.0) == pytest.approx(base + 0.2)


def test_the_planners_clearance_stops_the_robot_as_the_stopping_model_does() -> None:
    """``S_r + S_s`` of the planner's clearance: ``v T_r`` and the stopping model's ``S_s`` (the governor's
    and the monitor's), with ``T_s`` from the fastest point's and the fastest joint's speeds, not the
    constant-speed law's fixed ``T_s``."""
    p = SSMParams(t_reaction_s=0.111, t_stop_s=0.2, z_human_m=0.05)
    base = p.intrusion_m + p.z_robot_m + 0.05
    v = np.array([0.0, 0.3, 1.0, 1.0, 0.3])
    w = np.array([0.0, 0.3, 0.6, 3.0, 1.5])
    three = StoppingModel(decel_mps2=3.0, joint_decel_radps2=3.0)
    t_s = np.maximum(v / three.decel_mps2, w / three.slowest_joint_decel_radps2)  # 0, 0.1, 1/3, 1, 0.5
    np.testing.assert_allclose(
        forecast_clearance(v, 0.0, p, w_top_radps=w, stopping=three),
        base + v * 0.111 + v * t_s / 2,
        rtol=1e-12,
    )
    np.testing.assert_allclose(t_s, [0.0, 0.1, 1 / 3, 1.0, 0.5])
    # a robot creeping stops in a moment; one turning a joint at 3 rad/s needs a second
    assert forecast_clearance(0.05, 0.0, p, w_top_radps=0.05, stopping=three) < 0.05 * p.robot_time_s + base
    assert forecast_clearance(1.0, 0.0, p, w_top_radps=3.0, stopping=three) == pytest.approx(
        base + 0.111 + 0.5
    )
    # and the model's own delay counts whole
    slow = StoppingModel(decel_mps2=1.0, joint_decel_radps2=1.0, delay_s=0.1)
    assert forecast_clearance(1.0, 0.0, p, w_top_radps=0.0, stopping=slow) == pytest.approx(
        base + 0.111 + 1.0 * (0.1 + 0.5)
    )
    with pytest.raises(TypeError):
        forecast_clearance(1.0, 0.0, p)  # type: ignore[call-arg]  # the joints' speed is never assumed


def test_invalid_parameters_are_rejected_with_the_field_name() -> None:
    with pytest.raises(ValueError, match="t_stop_s"):
        SSMParams(t_stop_s=-1.0)
    with pytest.raises(ValueError, match="v_human_mps"):
        SSMParams(v_human_mps=float("nan"))
