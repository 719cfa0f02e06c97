"""The operator dashboard in a real headless Chromium against a real ``hrc serve`` (simulated cell).

One operator session: sign in, add a participant and a session, run a short trial to its end, start the next
trial, watch the live state change, press the E-stop and see the robot stop, reset, open the results and
download a CSV; every API error on the way is shown with its ``detail``. Screenshots of the dashboard and of
the viser 3D view are written to ``test-artifacts/`` (and to ``docs/screenshot-dashboard.png`` when
``HRC_UPDATE_DOCS_SCREENSHOT=1``).
"""

from __future__ import annotations

import contextlib
import csv
import io
import os
import re
import shutil
import time
from pathlib import Path
from typing import Any
from urllib.parse import quote

import numpy as np
import pytest

pytestmark = pytest.mark.e2e

REPO_ROOT = Path(__file__).resolve().parents[2]
#: Generous bounds for a loaded CI machine (software WebGL next to the server and the browser).
UI_TIMEOUT_MS = 30_000


def expect(locator: Any, message: str | None = None) -> Any:
    from playwright.sync_api import expect as _expect

    return _expect(locator, message)


def sign_in(page: Any, server: Any) -> None:
    page.goto(f"{server.base_url}/")
    page.get_by_test_id("login-token").fill(server.token)
    page.get_by_test_id("login-submit").click()
    expect(page.get_by_test_id("app-view")).to_be_visible()
    expect(page.get_by_test_id("conn-pill")).to_contain_text("live", timeout=UI_TIMEOUT_MS)


def wait_until(cond: Any, what: str, *, timeout_s: float = 30.0) -> Any:
    deadline = time.monotonic() + timeout_s
    while True:
        value = cond()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}")
        time.sleep(0.25)


def wait_for_3d_view(frame: Any, page: Any) -> None:
    """Wait until the viser client (``frame``: the embedded frame or the viser page itself) is connected
    and its picture has settled; close its software-rendering notice so that screenshots show the cell."""
    expect(frame.locator("canvas").first).to_be_visible(timeout=UI_TIMEOUT_MS)
    expect(frame.get_by_text("Connected").first).to_be_visible(timeout=UI_TIMEOUT_MS)
    close = frame.locator("#webgl-software-rendering .mantine-Notification-closeButton")
    with contextlib.suppress(Exception):  # only shown where WebGL runs in software
        close.wait_for(timeout=15_000)
        # A DOM click: Playwright's pointer click waits on the busy software-rendering frame.
        close.evaluate("e => e.click()", timeout=20_000)
    # The scene fades in; wait until the page's mean brightness stops changing (bounded).
    from PIL import Image

    previous = None
    for _ in range(20):
        page.wait_for_timeout(1_500)
        mean = float(np.asarray(Image.open(io.BytesIO(page.screenshot())).convert("L"), dtype=float).mean())
        if previous is not None and abs(mean - previous) < 0.5:
            break
        previous = mean


#: The 3D view's status panel (viser markdown): state, mode, speed and the snapshot's time.
VISER_STATUS = re.compile(
    r"State:\s*(?P<state>.+?)\s*Mode:\s*(?P<mode>.+?)\s*Speed:\s*(?P<speed>\S+).*?t = (?P<t>[\d.]+) s", re.S
)
#: Records what the page's supervisor panel showed for every snapshot it drew, by the snapshot's time.
RECORD_PANEL_JS = """() => {
  const el = document.querySelector('[data-testid=live-state]');
  const text = (id) => document.querySelector(`[data-testid=${id}]`).textContent;
  window.__shown = new Map();
  new MutationObserver(() => {
    window.__shown.set(el.dataset.t, [text('live-state'), text('live-mode'), text('speed-scale')]);
    if (window.__shown.size > 5000) window.__shown.delete(window.__shown.keys().next().value);
  }).observe(el, { attributes: true, attributeFilter: ['data-t'] });
}"""
MODE_TEXT = re.compile(r"^(free|SSM|PFL · [a-z /]+|stopped)$")
PART_MODE = re.compile(r"^(free|ssm|pfl:[a-z_]+|stopped)$")


def viser_status_panel(frame: Any) -> Any:
    """The 3D view's status text: the innermost element that holds both its first and its last line."""
    return frame.locator("*", has_text="State:").filter(has_text="Snapshot:").last


def check_panel_and_3d_view_agree(page: Any, frame: Any, *, timeout_s: float = 40.0) -> int:
    """The page's supervisor panel and the 3D view's status panel show the same state, mode and speed for
    the same snapshot (both read the snapshot's ``state``, ``mode`` and ``speed_scale``). Returns how many
    snapshots were compared (at least 3): the two draw at their own rates, so the comparison waits for
    snapshots that both drew."""
    page.evaluate(RECORD_PANEL_JS)
    status = viser_status_panel(frame)
    samples: list[dict[str, str]] = []
    compared = 0
    deadline = time.monotonic() + timeout_s
    while compared < 3 and time.monotonic() < deadline:
        found = VISER_STATUS.search(status.inner_text())
        if found:
            samples.append(found.groupdict())
        page.wait_for_timeout(300)
        for sample in list(samples):
            shown = page.evaluate("t => (window.__shown.get(t) || null)", sample["t"])
            if shown is None:
                continue
            samples.remove(sample)
            assert [s.strip() for s in shown] == [sample["state"], sample["mode"], sample["speed"]], (
                f"at t = {sample['t']} s the page shows {shown}, the 3D view {sample}"
            )
            compared += 1
        del samples[:-40]
    assert compared >= 3, f"the page and the 3D view drew no common snapshot in {timeout_s:.0f} s"
    return compared


def latest_trial(server: Any) -> dict[str, Any]:
    trials = server.api("GET", "/api/trials").json()
    assert trials, "no trial in the database"
    return max(trials, key=lambda t: t["id"])


def test_sign_in_shows_why_a_token_is_refused(page: Any, hrc_server: Any) -> None:
    page.goto(f"{hrc_server.base_url}/")
    expect(page.get_by_test_id("login-view")).to_be_visible()
    expect(page.get_by_test_id("estop-button")).to_be_visible()  # the E-stop is always on screen
    page.get_by_test_id("login-token").fill("not-the-operator-token-000")
    page.get_by_test_id("login-submit").click()
    refused = hrc_server.api(
        "GET", "/api/info", headers={"Authorization": "Bearer not-the-operator-token-000"}
    )
    assert refused.status_code == 401
    expect(page.get_by_test_id("login-error")).to_contain_text(refused.json()["detail"])
    expect(page.get_by_test_id("app-view")).to_be_hidden()

    page.get_by_test_id("login-token").fill(hrc_server.token)
    page.get_by_test_id("login-submit").click()
    expect(page.get_by_test_id("app-view")).to_be_visible()
    # The token lives in sessionStorage: a reload keeps the operator signed in, signing out forgets it.
    assert page.evaluate("sessionStorage.getItem('hrc.operatorToken')") == hrc_server.token
    page.reload()
    expect(page.get_by_test_id("app-view")).to_be_visible()
    page.get_by_test_id("logout-button").click()
    expect(page.get_by_test_id("login-view")).to_be_visible()
    assert page.evaluate("sessionStorage.getItem('hrc.operatorToken')") is None


def test_operator_session_end_to_end(page: Any, hrc_server: Any, artifacts_dir: Path) -> None:
    server = hrc_server
    sign_in(page, server)
    live_state = page.get_by_test_id("live-state")
    expect(live_state).not_to_have_text("–", timeout=UI_TIMEOUT_MS)  # the first snapshot arrived

    # --- participants and sessions --------------------------------------------------------------------
    page.get_by_test_id("tab-study").click()
    page.get_by_test_id("participant-code").fill("E2E01")
    page.get_by_test_id("participant-age").fill("34")
    page.get_by_test_id("participant-create").click()
    expect(page.get_by_test_id("participants-table")).to_contain_text("E2E01")
    participant = next(p for p in server.api("GET", "/api/participants").json() if p["code"] == "E2E01")
    expect(page.get_by_test_id("trial-participant")).to_have_value(str(participant["id"]))
    order = server.api("GET", f"/api/participants/{participant['id']}/method-order").json()["methods"]
    hint = page.get_by_test_id("method-order")
    expect(hint).to_contain_text(f"1. {order[0]}")
    expect(hint).to_contain_text(f"2. {order[1]}")
    expect(page.get_by_test_id("trial-method")).to_have_value(order[0])

    # A duplicate code: the API's 409 detail is shown as it is.
    page.get_by_test_id("participant-code").fill("E2E01")
    page.get_by_test_id("participant-create").click()
    conflict = server.api("POST", "/api/participants", json={"code": "E2E01"})
    assert conflict.status_code == 409
    expect(page.get_by_test_id("alert")).to_contain_text("HTTP 409")
    expect(page.get_by_test_id("alert")).to_contain_text(conflict.json()["detail"])

    page.get_by_test_id("session-name").fill("E2E session")
    page.get_by_test_id("session-create").click()
    expect(page.get_by_test_id("sessions-table")).to_contain_text("E2E session")
    expect(page.get_by_test_id("alert")).to_be_hidden()

    # --- a short trial, run to its end -----------------------------------------------------------------
    state_before = live_state.inner_text()
    page.get_by_test_id("trial-duration").fill("10")
    page.get_by_test_id("trial-start").click()
    expect(page.get_by_test_id("view-live")).to_be_visible()
    first = latest_trial(server)
    assert first["method"] == order[0] and first["participant_id"] == participant["id"]
    expect(page.get_by_test_id("trial-pill")).to_contain_text(f"trial #{first['id']}", timeout=UI_TIMEOUT_MS)
    expect(page.get_by_test_id("trial-time")).to_contain_text("of 10 s", timeout=UI_TIMEOUT_MS)
    # where the trial's time goes, live: one row per part of the time budget, their sum the time so far
    expect(page.get_by_test_id("budget-waiting_for_plan")).to_contain_text(" s", timeout=UI_TIMEOUT_MS)
    expect(page.get_by_test_id("budget-waiting_for_person")).to_contain_text(" s", timeout=UI_TIMEOUT_MS)
    rows = page.get_by_test_id("time-budget").locator("dd")
    expect(rows).to_have_count(9)
    wait_until(
        lambda: float(page.get_by_test_id("budget-total").inner_text().split(" s")[0]) > 0.5,
        "the time budget to count the trial's time",
    )
    # and per task pose, each with its own bar: the first leg goes to the pickup's approach pose
    first_goal = page.get_by_test_id("budget-goal-pickup_approach")
    expect(first_goal).to_contain_text(" s", timeout=UI_TIMEOUT_MS)
    expect(first_goal.locator(".budget-bar-mini span").first).to_be_attached()
    wait_until(lambda: live_state.inner_text() != state_before, "the supervisor state to change in the page")
    wait_until(
        lambda: server.api("GET", f"/api/trials/{first['id']}").json()["status"] != "running",
        "the first trial to end",
        timeout_s=60,
    )
    expect(page.get_by_test_id("trial-pill")).to_have_text("no trial", timeout=UI_TIMEOUT_MS)

    # --- the next trial in the counterbalanced order; E-stop during it ---------------------------------
    page.get_by_test_id("tab-study").click()
    expect(page.get_by_test_id("trial-method")).to_have_value(order[1], timeout=UI_TIMEOUT_MS)
    page.get_by_test_id("trial-duration").fill("60")
    page.get_by_test_id("trial-start").click()
    expect(page.get_by_test_id("view-live")).to_be_visible()
    second = latest_trial(server)
    assert second["id"] > first["id"] and second["method"] == order[1]
    expect(page.get_by_test_id("trial-pill")).to_contain_text(f"trial #{second['id']}", timeout=UI_TIMEOUT_MS)
    wait_until(
        lambda: page.get_by_test_id("trial-progress").evaluate("e => parseFloat(e.style.width) > 0"),
        "the trial progress bar to move",
    )

    frame = page.frame_locator("[data-testid=viser-frame]")
    wait_for_3d_view(frame, page)
    page.screenshot(path=str(artifacts_dir / "dashboard-live.png"), full_page=True)

    # --- the operator sees the mode: what limits each part, one state and one speed everywhere ----------
    mode = page.get_by_test_id("live-mode")
    wait_until(lambda: MODE_TEXT.match(mode.inner_text()), "the page to show the robot's mode")
    parts = page.get_by_test_id("part-modes").locator("li")
    expect(parts).to_have_count(9, timeout=UI_TIMEOUT_MS)  # one per capsule of the UR5e and its tool
    for i in range(9):
        assert PART_MODE.match(parts.nth(i).get_attribute("data-mode") or ""), parts.nth(i).inner_text()
    expect(page.get_by_test_id("part-modes").locator("li.limiting")).to_have_count(1)
    live = server.api("GET", "/api/state").json()
    assert live["mode"] is not None and [p["name"] for p in live["parts"]][-1] == "tool"
    if live["required_separation_m"] is not None and live["limiting_part"] is not None:
        expect(page.get_by_test_id("required-separation")).to_contain_text(" m (", timeout=UI_TIMEOUT_MS)
    check_panel_and_3d_view_agree(page, frame)

    page.get_by_test_id("estop-button").click()
    expect(live_state).to_have_text("E-STOP", timeout=UI_TIMEOUT_MS)
    expect(page.get_by_test_id("live-mode")).to_have_text("stopped", timeout=UI_TIMEOUT_MS)
    expect(page.get_by_test_id("speed-scale")).to_have_text("0%", timeout=UI_TIMEOUT_MS)
    viser_status = viser_status_panel(frame)
    expect(viser_status).to_contain_text("E-STOP", timeout=UI_TIMEOUT_MS)
    found = VISER_STATUS.search(viser_status.inner_text())
    assert found and (found["state"], found["mode"], found["speed"]) == ("E-STOP", "stopped", "0%")
    expect(page.get_by_test_id("toast")).to_contain_text("E-stop")
    robot = server.api("GET", "/api/robot").json()
    assert robot["estopped"] is True
    # The robot stops: its configuration no longer changes.
    time.sleep(1.0)
    q1 = np.array(server.api("GET", "/api/robot").json()["q"])
    time.sleep(1.0)
    q2 = np.array(server.api("GET", "/api/robot").json()["q"])
    assert np.allclose(q1, q2, atol=1e-6), f"the robot still moves after the E-stop: {q1} -> {q2}"
    wait_until(
        lambda: server.api("GET", f"/api/trials/{second['id']}").json()["status"] != "running",
        "the E-stop to end the running trial",
    )
    expect(page.get_by_test_id("trial-pill")).to_have_text("no trial", timeout=UI_TIMEOUT_MS)
    page.screenshot(path=str(artifacts_dir / "dashboard-estop.png"))

    # While E-stopped a trial cannot start: the page shows the API's reason.
    page.get_by_test_id("tab-study").click()
    page.get_by_test_id("trial-start").click()
    expect(page.get_by_test_id("alert")).to_contain_text("Starting the trial failed (HTTP 409)")

    page.get_by_test_id("reset-button").click()
    expect(live_state).not_to_have_text("E-STOP", timeout=UI_TIMEOUT_MS)
    assert server.api("GET", "/api/robot").json()["estopped"] is False

    # --- trials table, results and downloads -----------------------------------------------------------
    page.get_by_test_id("trials-refresh").click()
    table = page.get_by_test_id("trials-table")
    expect(table.locator(f"tr[data-trial-id='{first['id']}']")).to_contain_text("E2E01")
    expect(table.locator(f"tr[data-trial-id='{second['id']}']")).to_contain_text(order[1])

    page.get_by_test_id("tab-results").click()
    summary = server.api("GET", "/api/summary").json()
    rows = page.get_by_test_id("results-table").locator("tbody tr")
    expect(rows).to_have_count(len(summary["metrics"]), timeout=UI_TIMEOUT_MS)
    expect(page.get_by_test_id("results-table")).to_contain_text("Completed tasks")
    expect(page.get_by_test_id("results-note")).to_contain_text("completed trials")
    if summary["n_trials"]["proactive"] or summary["n_trials"]["reactive"]:
        # The server draws the plots (matplotlib) while the cell's loop runs beside it: on a loaded machine
        # that takes a while, so it is timed here on its own, and the page then shows the same (cached) image.
        started = time.monotonic()
        png = server.api("GET", "/api/summary/boxplots.png", timeout=180.0)
        drawn_s = time.monotonic() - started
        assert png.status_code == 200 and png.content.startswith(b"\x89PNG"), png.text[:200]
        expect(
            page.get_by_test_id("boxplots"),
            f"the page's box plots (drawn in {drawn_s:.1f} s); server log:\n{server.log_tail(30)}",
        ).to_be_visible(timeout=120_000)
    # where the completed trials' time went, per method, from the same summary
    for method in ("proactive", "reactive"):
        row = page.get_by_test_id(f"results-budget-{method}")
        if summary["time_budget_s"][method]["trials"]:
            expect(row).to_contain_text("held still", timeout=UI_TIMEOUT_MS)
            expect(row).to_contain_text("waiting for the person")
            expect(row.locator(".budget-bar span").first).to_be_attached()
        else:
            expect(row).to_have_count(0)
    assert summary["time_budget_s"][first["method"]]["trials"] >= 1  # the first trial ran to its end

    with page.expect_download() as download_info:
        page.get_by_test_id("download-trials").click()
    download = download_info.value
    assert download.suggested_filename == "trials.csv"
    path = artifacts_dir / "e2e-trials.csv"
    download.save_as(str(path))
    records = list(csv.DictReader(io.StringIO(path.read_text(encoding="utf-8"))))
    by_id = {int(r["trial_id"]): r for r in records}
    assert {first["id"], second["id"]} <= set(by_id)
    assert by_id[first["id"]]["participant_code"] == "E2E01"
    page.screenshot(path=str(artifacts_dir / "dashboard-results.png"), full_page=True)


def test_3d_view_shows_the_cell(page: Any, hrc_server: Any, artifacts_dir: Path) -> None:
    """The viser page on its own: the scene tree holds the cell, the robot, the person and the layers."""
    info = hrc_server.api("GET", "/api/info").json()
    port = info["viser_port"]
    socket_url = quote(f"ws://127.0.0.1:{port}/?token={hrc_server.token}", safe="")
    page.goto(f"http://127.0.0.1:{port}/?websocket={socket_url}")  # viewers need the operator token
    wait_for_3d_view(page, page)
    expect(page.get_by_text("State:").first).to_be_visible()
    expect(page.get_by_text("Forecast ghosts").first).to_be_visible()
    path = artifacts_dir / "viser-3d.png"
    page.screenshot(path=str(path))
    from PIL import Image

    img = np.asarray(Image.open(path).convert("RGB"), dtype=float)
    # Not a blank page: the rendered cell has clearly different colours (table, robot, person, floor grid).
    assert img.std() > 12.0, "the 3D view screenshot looks blank"


@pytest.mark.skipif(
    os.environ.get("HRC_UPDATE_DOCS_SCREENSHOT") != "1",
    reason="writes docs/screenshot-dashboard.png; run with HRC_UPDATE_DOCS_SCREENSHOT=1 to refresh it",
)
def test_readme_screenshot(page: Any, hrc_server: Any, artifacts_dir: Path) -> None:
    """The README's picture: a proactive trial running, the forecast, plans and separation in the 3D view."""
    server = hrc_server
    created = server.api("POST", "/api/participants", json={"code": "DEMO01", "experience": "none"})
    assert created.status_code == 201, created.text
    started = server.api(
        "POST",
        "/api/trials",
        json={"participant_id": created.json()["id"], "method": "proactive", "duration_s": 120},
    )
    assert started.status_code == 201, started.text
    try:
        sign_in(page, server)
        wait_for_3d_view(page.frame_locator("[data-testid=viser-frame]"), page)
        expect(page.get_by_test_id("trial-pill")).to_contain_text(f"trial #{started.json()['id']}")
        wait_until(
            lambda: server.api("GET", "/api/state").json().get("plan_tcp") is not None,
            "a plan to be executed",
            timeout_s=60,
        )
        page.wait_for_timeout(3_000)
        shot = artifacts_dir / "dashboard-readme.png"
        page.screenshot(path=str(shot))
        shutil.copy(shot, REPO_ROOT / "docs" / "screenshot-dashboard.png")
    finally:
        server.api("POST", f"/api/trials/{started.json()['id']}/stop")
