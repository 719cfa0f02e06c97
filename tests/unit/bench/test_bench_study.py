"""``hrc bench study``: the three engines run the same real trials; the JSON has every number."""

from __future__ import annotations

import pytest


@pytest.mark.slow
def test_bench_study_measures_inline_process_pool_and_ray(monkeypatch: pytest.MonkeyPatch) -> None:
    from app.bench import study

    monkeypatch.setattr(study.os, "cpu_count", lambda: 2)  # 4 trials of 1 s on 2 workers
    out = study.run(quick=True, progress=False, duration_s=1.0)
    assert out["trials"] == 4 and out["workers"] == 2
    assert set(out["trials_per_min"]) == {"inline", "process_pool", "ray"}
    assert all(v > 0 for v in out["trials_per_min"].values())
    assert out["failed_trials"] == {"inline": 0, "process_pool": 0, "ray": 0}
    assert out["ray_startup_s"] > 0
    assert out["ray_vs_process_pool"] == pytest.approx(
        out["trials_per_min"]["ray"] / out["trials_per_min"]["process_pool"], rel=1e-2
    )
