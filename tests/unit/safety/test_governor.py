"""The speed governor on its own (:mod:`app.safety.governor` and its compiled kernels): the braking
envelope against a brute-force check and the NumPy reference, the scale window against the whole grid, the
compiled speed-scaling law against :func:`app.safety.ssm.speed_scale`. The governor inside the supervisor's
servo tick is tested in ``tests/unit/control/test_supervisor.py``."""

from __future__ import annotations

import math

import numpy as np
import pytest
from governor_reference import max_scale_reference

from app.safety import _kernels
from app.safety.governor import SeparationModel, SpeedScaleLaw, ssm_alone
from app.safety.ssm import SSMParams

#: a person who speeds up at most at 8 m/s^2, up to 2 m/s; T_r = 0.1 s, C + Z_d + Z_r = 0.1 m, a brake of
#: 2 m/s^2
SSM = SeparationModel(
    s0_m=0.1, t_reaction_s=0.1, stop_decel_mps2=2.0, human_speed_max_mps=2.0, human_accel_mps2=8.0
)


def test_envelope_matches_a_brute_force_check_for_a_steady_person() -> None:
    model = SeparationModel(s0_m=0.1, t_reaction_s=0.1, stop_decel_mps2=2.0, human_accel_mps2=0.0)
    vh, a = 1.2, 1.5
    assert model.max_speed(0.1 + 0.1 * vh - 1e-6, v_human_mps=vh, decel_mps2=a) == 0.0

    def needed(v: float) -> float:  # the separation a brake from v needs, on a fine time grid
        t = np.linspace(0.0, v / a, 4001)
        vt = v - a * t
        return float(np.max(model.sp(vt, vt, vh) + vh * t + v * t - 0.5 * a * t**2))

    for v in (0.2, 0.5, 1.0, 2.0):
        got = model.max_speed(needed(v), v_human_mps=vh, decel_mps2=a)
        assert got <= v + 1e-9  # never more than exact
        assert got >= v - 3.0 / 96 - 0.02  # within a grid step (and the sampled instants) of it
    speeds = [model.max_speed(d, v_human_mps=0.5, decel_mps2=2.0) for d in np.linspace(0, 3, 50)]
    assert np.all(np.diff(speeds) >= 0)


def test_envelope_is_stricter_for_faster_people_and_weaker_brakes() -> None:
    d = 0.8
    assert SSM.max_speed(d, v_human_mps=1.0, decel_mps2=3.0) < SSM.max_speed(
        d, v_human_mps=0.0, decel_mps2=3.0
    )
    assert SSM.max_speed(d, v_human_mps=0.0, decel_mps2=1.0) < SSM.max_speed(
        d, v_human_mps=0.0, decel_mps2=3.0
    )
    assert SSM.required(0.0) == pytest.approx(0.1)
    # 0.1 + 1.0 * (0.1 + 0.5) + 1.0 * (0.1 + 0.25)
    assert SSM.required(1.0, 1.0) == pytest.approx(1.05)
    x, v = SSM.human_approach(1.0, np.array([0.0, 0.125, 1.0]))
    np.testing.assert_allclose(v, [1.0, 2.0, 2.0])
    np.testing.assert_allclose(x, [0.0, 0.125 + 0.5 * 8 * 0.125**2, 0.1875 + 2.0 * 0.875])


def test_the_scale_window_agrees_with_the_whole_grid() -> None:
    """The servo asks only for the scales one tick can reach; the answer agrees with the whole grid's."""
    model = SeparationModel(s0_m=0.11, t_reaction_s=0.1, stop_decel_mps2=2.0, human_accel_mps2=8.0)
    rng = np.random.default_rng(5)
    for _ in range(300):
        n = int(rng.integers(1, 6))
        kw = dict(
            v_human_mps=rng.uniform(0.0, 1.0, n),
            v_parts_mps=rng.uniform(0.05, 1.0, n),
            rate=rng.uniform(2, 20),
        )
        d = rng.uniform(0.1, 1.0, n)
        full = model.max_scale(d, **kw)
        lo = float(rng.uniform(0.0, 0.9))
        hi = min(lo + float(rng.uniform(0.0, 0.2)), 1.0)
        got = model.max_scale(d, **kw, lo=lo, hi=hi)
        assert got <= hi + 1e-12
        if got > 0.0:
            assert got >= lo - 1e-12
            assert model.max_scale(d, **kw, lo=got, hi=got) == got  # itself safe
        if full >= hi:
            assert got == pytest.approx(hi) or got >= full - 0.025  # the grid's step
        elif full >= lo:
            assert full - 0.025 - 1e-12 <= got <= full + 0.025 + 1e-12
        else:
            assert got == 0.0 or got <= full + 0.025


def test_the_compiled_envelope_equals_the_numpy_reference() -> None:
    """Every branch of the compiled braking envelope (quick accept, a scale inside the window, ``lo`` unsafe,
    an empty window) gives the NumPy reference's answer, for several parts and person speeds."""
    rng = np.random.default_rng(11)
    models = [
        SeparationModel(s0_m=0.11, t_reaction_s=0.1, stop_decel_mps2=2.0, human_accel_mps2=8.0),
        SeparationModel(s0_m=0.05, t_reaction_s=0.2, stop_decel_mps2=1.0, human_accel_mps2=0.0),
    ]
    outcomes = set()
    for i in range(2000):
        model = models[i % 2]
        n = int(rng.integers(1, 8))
        lo = float(rng.uniform(-0.1, 1.0))
        hi = float(rng.uniform(lo - 0.05, lo + 0.4))
        kw = dict(
            v_human_mps=rng.uniform(0.0, 2.5, n),
            v_parts_mps=rng.uniform(0.0, 1.5, n),
            rate=float(rng.choice([rng.uniform(0.5, 30.0), math.inf])),
            lo=lo,
            hi=hi,
        )
        d = rng.uniform(-0.1, 1.5, n)
        with np.errstate(invalid="ignore"):  # an infinite brake rate: inf * 0 in the reference's grid
            want = max_scale_reference(model, d, **kw)
        got = model.max_scale(d, **kw)
        assert got == pytest.approx(want, abs=1e-12), (d, kw)
        outcomes.add("hi" if got == min(hi, 1.0) else "zero" if got == 0.0 else "inside")
    assert outcomes == {"hi", "zero", "inside"}
    assert models[0].max_scale(np.zeros(0), v_human_mps=np.zeros(0), v_parts_mps=np.zeros(0), rate=1.0) == 1.0


def test_the_compiled_speed_scale_law_agrees_with_the_safety_module() -> None:
    """The compiled governor's law is :func:`app.safety.ssm.speed_scale` (the smallest over parts)."""
    from app.safety.ssm import speed_scale

    params = SSMParams()
    law = SpeedScaleLaw(params)
    rng = np.random.default_rng(2)
    for _ in range(200):
        n = int(rng.integers(1, 8))
        d = rng.uniform(-0.1, 1.5, n)
        d[rng.uniform(size=n) < 0.05] = math.inf
        v = rng.uniform(0.0, 1.5, n) * (rng.uniform(size=n) > 0.1)
        vh = rng.uniform(-0.5, 2.0, n)
        want = float(np.min(speed_scale(d, v, params, v_human_mps=vh)))
        alone = ssm_alone(n)
        got = _kernels.law_scale(d, v, vh, law.kernel_params, alone.levels, alone.extra, alone.v_h)
        assert got == pytest.approx(want, abs=1e-12)
    assert law(np.zeros(0), np.zeros(0), np.zeros(0)) == 1.0


def test_a_part_that_closes_counts_at_its_whole_speed_and_one_moving_away_at_its_directed_speed() -> None:
    """The path's closing rate is that of a part's separation from the nearest capsule of the tracked pose:
    toward another capsule, or the true person a frame later, a closing part may close at up to its whole
    speed, so the governor takes that; a part moving away (or sideways) keeps its directed speed."""
    from app.safety.governor import PathClosing

    closing = PathClosing(0.0, math.inf, np.array([0.3, -0.4, 0.0]), np.zeros(3))
    vmax = np.array([0.5, 0.5, 0.5])
    got = closing.motion(0.0, vmax, np.full(3, 1.0), dt=0.008, rate=5.0, hi=1.0)
    assert got is not None
    np.testing.assert_array_equal(got.v_toward, [0.5, -0.4, 0.0])
    np.testing.assert_array_equal(got.v_part, vmax)
