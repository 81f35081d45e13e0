"""The dashboard in a real headless Chromium against a real stack (``ra2vipas up``: router,
orchestrator, learner, two rigs, SQLite file, an API token): the home page (filters, a
campaign appearing and progressing live), creating a campaign through the form (a 422 shown
next to its field), progress and DR curves updating without a reload, the campaign page (hover
values, zoom, exports), the episode player, cancelling and deleting, the rigs page (idle,
episode running), phone width and the keyboard; a study started through the API progressing
on the studies page, its plot and a point's campaign page, cancelling and deleting a study; no
console errors and no request leaving the orchestrator anywhere (``conftest.watched``)."""

from __future__ import annotations

import re
import threading
import time

import pytest

from tests import http
from tests.web.conftest import PHONE, TOKEN

SMALL = {"steps": 30, "n_train": 250, "n_targets": 10}


def wait_until(predicate, timeout: float = 60.0, every: float = 0.2, what: str = "condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(every)
    raise AssertionError(f"{what} not met within {timeout} s")


def next_line_with(proc, needle: str, timeout: float) -> str:
    """The next line of the process's output that contains ``needle`` (read by a thread: the
    line may already sit in the pipe reader's buffer, where a select() would not see it)."""
    found: list[str] = []

    def read() -> None:
        for line in proc.stdout:
            if needle in line:
                found.append(line)
                return

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    reader.join(timeout)
    assert found, f"{needle!r} not printed within {timeout} s"
    return found[0]


def wait_done(api, cid: str, timeout: float = 180.0) -> dict:
    return wait_until(lambda: (c := api.get(f"/campaigns/{cid}").json())["status"] in ("done", "failed", "cancelled") and c,
                      timeout, what=f"campaign {cid} finished")


@pytest.fixture(scope="module")
def done_campaign(api):
    """A small finished campaign (6 tests of Ra²ViPAS and RaPAS)."""
    r = api.post("/campaigns", json={"overrides": SMALL, "algorithms": ["ra2vipas", "rapas"], "tests": 6, "seed": 4, "name": "fixture"})
    assert r.status_code == 201, r.text
    c = wait_done(api, r.json()["id"])
    assert c["status"] == "done", c
    return c


def enter_token(page) -> None:
    dialog = page.locator("#token-dialog")
    dialog.wait_for(state="visible")
    page.fill("#token-input", TOKEN)
    page.click("#token-form button[type=submit]")
    dialog.wait_for(state="hidden")


def test_up_prints_the_dashboard_address(stack):
    line = next_line_with(stack["up"], "dashboard on", 10)
    url = re.search(r"dashboard on (http://[0-9.:]+/)", line).group(1)
    assert url == stack["api"] + "/"
    page = http.get(url, timeout=10)
    assert page.status_code == 200 and "<h1>Campaigns</h1>" in page.text


def test_home_page_lists_campaigns_with_their_final_dr(watched, done_campaign, screenshots):
    w = watched()
    w.page.goto("/")
    row = w.page.locator(f"#campaign-{done_campaign['id']}")
    row.wait_for()
    assert "fixture" in row.inner_text() and "done" in row.inner_text()
    results = w.page.request.get(f"/campaigns/{done_campaign['id']}/results").json()
    assert f"{results['algorithms']['ra2vipas']['dr_final']:.3f}" in row.inner_text()
    # the status filter narrows the table without a reload
    w.page.evaluate("window.__marker = 'same page'")
    w.page.select_option("select[name=status]", "failed")
    w.page.locator("#campaign-rows").get_by_text("No campaigns").wait_for()
    assert w.page.evaluate("window.__marker") == "same page" and "status=failed" in w.page.url
    w.page.select_option("select[name=status]", "")
    row.wait_for()
    # so does the preset filter: the fixture (preset paper) leaves, only dynamic campaigns remain
    w.page.select_option("select[name=preset]", "dynamic")
    row.wait_for(state="detached")
    assert "preset=dynamic" in w.page.url and w.page.evaluate("window.__marker") == "same page"
    presets = w.page.locator("#campaign-rows tr[id^=campaign-] td:nth-child(2)").all_inner_texts()
    assert set(presets) <= {"dynamic"}
    w.page.select_option("select[name=preset]", "paper")
    row.wait_for()
    w.page.screenshot(path=screenshots / "home.png", full_page=True)


def test_create_a_campaign_through_the_form_see_a_422_then_follow_it_live(watched, stack, api, screenshots):
    w = watched(expect=(422,))
    page = w.page
    page.goto("/ui/new")
    posts = []
    page.on("request", lambda r: posts.append(r.url) if r.method == "POST" else None)
    # the page refuses what it can check itself, beside the field, without a request
    page.fill("#p-n_targets", "0")
    page.click("#submit-campaign")
    assert page.locator("#error-n_targets").is_visible() and posts == []
    assert page.locator("#p-n_targets").get_attribute("aria-invalid") == "true"
    # a value only the API can refuse (train_min_range_m must stay below train_max_range_m): a 422, shown at that field
    page.fill("#p-n_targets", "15")
    page.fill("#p-train_min_range_m", "8")
    page.fill("#f-tests", "40")
    page.fill("#f-name", "from the form")
    page.fill("#p-steps", "60")
    page.click("#submit-campaign")
    enter_token(page)  # asked once: the orchestrator has a token
    error = page.locator("#error-train_min_range_m")
    error.wait_for(state="visible")
    assert "train_max_range_m" in error.inner_text()
    assert "Not started" in page.locator("#form-error").inner_text()
    assert all(c["name"] != "from the form" for c in api.get("/campaigns", params={"limit": 200}).json()["items"])  # nothing stored
    page.screenshot(path=screenshots / "new-campaign-422.png", full_page=True)
    # fixed: created (the token is not asked again in this tab) and the page follows it
    page.fill("#p-train_min_range_m", "0.5")
    page.click("#submit-campaign")
    page.wait_for_url(re.compile(r"/ui/campaigns/[0-9a-f]{12}$"))
    assert not page.locator("#token-dialog").is_visible()
    cid = page.url.rsplit("/", 1)[1]
    c = api.get(f"/campaigns/{cid}").json()
    assert c["name"] == "from the form" and c["tests"] == 40 and c["overrides"] == {"n_targets": 15, "steps": 60}
    # overrides highlighted in the scenario table
    changed = page.locator("#scenario-table tr.changed th code").all_text_contents()
    assert sorted(changed) == ["n_targets", "steps"]

    # progress and the DR curves grow without a reload
    page.evaluate("window.__marker = 'same page'")
    seen = set()

    def progressed():
        seen.add(page.locator("#progress-text").inner_text())
        return len(seen) >= 3 and page.locator("#dr-chart canvas").count() == 1

    wait_until(progressed, 120, what="three progress updates and the DR chart")
    legend = page.locator("#dr-legend").inner_text()
    assert "Ra²ViPAS" in legend and re.search(r"n=\d+", legend)
    page.screenshot(path=screenshots / "campaign-running.png", full_page=True)
    # done: the summary is swapped in, still without a reload
    page.locator("#summary-table").wait_for(timeout=180_000)
    assert page.locator("#status").inner_text() == "done"
    assert page.evaluate("window.__marker") == "same page"
    assert api.get(f"/campaigns/{cid}").json()["status"] == "done"


def test_campaign_page_curves_summary_tests_and_exports(watched, api, done_campaign, screenshots):
    cid = done_campaign["id"]
    results = api.get(f"/campaigns/{cid}/results").json()
    w = watched()
    page = w.page
    page.goto(f"/ui/campaigns/{cid}")
    page.locator("#dr-chart canvas").wait_for()
    # the legend shows each algorithm's final DR; unticking one redraws the plot without it
    assert f"DR {results['algorithms']['ra2vipas']['dr_final']:.3f}" in page.locator("#dr-legend").inner_text()
    # hovering shows the values under the cursor, the API's at that time; a drag zooms, "reset zoom" undoes it
    over = page.locator("#dr-chart .u-over").bounding_box()
    value = page.locator('#dr-legend [data-alg="ra2vipas"]')
    block, period = results["algorithms"]["ra2vipas"], results["scenario"]["rf_period_s"]

    def at(fraction: float) -> None:
        page.mouse.move(over["x"] + over["width"] * fraction, over["y"] + over["height"] / 2)

    def shown() -> tuple[float, str, str, str]:
        m = re.fullmatch(r"DR (\S+) \[(\S+), (\S+)\] at (\S+) s, n=6", value.inner_text())
        assert m, value.inner_text()
        return float(m.group(4)), m.group(1), m.group(2), m.group(3)

    def hovered_time(fraction: float, predicate) -> float:
        at(fraction)
        return wait_until(lambda: predicate(shown()[0]) and shown()[0], 10, what=f"the legend's value at {fraction:.0%} of the plot")

    t = hovered_time(0.5, lambda t: 0.3 * len(block["dr"]) * period < t < 0.7 * len(block["dr"]) * period)
    k = round(t / period) - 1
    assert shown()[1:] == (f"{block['dr'][k]:.3f}", f"{block['dr_ci95'][k][0]:.3f}", f"{block['dr_ci95'][k][1]:.3f}")
    first = hovered_time(0.01, lambda t: t < 2.5 * period)
    at(0.4)
    page.mouse.down()
    at(0.7)
    page.mouse.up()
    zoomed = hovered_time(0.01, lambda t: t > first + 5 * period)  # the plot's left edge is now 40 % in
    assert zoomed == pytest.approx(0.4 * len(block["dr"]) * period, abs=0.1 * len(block["dr"]) * period)
    page.click("#dr-reset")
    hovered_time(0.01, lambda t: t == first)
    page.mouse.move(0, 0)
    before = page.locator("#dr-chart canvas").evaluate("c => c.toDataURL()")
    page.locator("#dr-legend input").first.uncheck()
    after = page.locator("#dr-chart canvas").evaluate("c => c.toDataURL()")
    assert before != after
    # summary: every algorithm, with the calibration columns the results carry
    summary = page.locator("#summary-table").inner_text()
    assert "Ra²ViPAS" in summary and "RaPAS" in summary and f"{results['algorithms']['rapas']['dr_final']:.3f}" in summary
    if "calibration" in results["algorithms"]["ra2vipas"]:
        assert "ECE (final)" in summary
    # the POD plot
    page.locator("#pod-chart canvas").wait_for()
    # per-test table and the "missed by Ra²ViPAS" filter, against the API's outcomes
    outcomes = api.get(f"/campaigns/{cid}/tests", params={"algorithm": "ra2vipas"}).json()["items"]
    missed = sorted(o["test_index"] for o in outcomes if not o["final_hit"])
    assert page.locator("#tests-table tbody tr").count() == 6
    page.check("#tests-filters input[name=missed]")
    page.wait_for_function(
        "n => document.querySelectorAll('#tests-table tbody tr').length === n && "
        "document.querySelector('#tests-filters input[name=missed]').checked", arg=max(1, len(missed)))
    shown = [int(t) for t in page.locator("#tests-table tbody th").all_inner_texts()]
    assert shown == missed
    page.uncheck("#tests-filters input[name=missed]")
    page.locator("#tests-table tbody tr").nth(5).wait_for()
    for link, kind in (("results JSON", "application/json"), ("CSV", "text/csv")):
        r = page.request.get(page.get_by_role("link", name=link).get_attribute("href"))
        assert r.status == 200 and r.headers["content-type"].startswith(kind)
    # every figure's PNG and SVG: the DR curves, the POD plot (and the reliability diagram when there is one)
    figures = [a.get_attribute("href") for a in page.locator(".exports a[href*='/plots/']").all()]
    assert {f"/campaigns/{cid}/plots/{name}?format={fmt}" for name in ("dr", "pod") for fmt in ("png", "svg")} <= set(figures)
    for href in figures:
        r = page.request.get(href)
        png = href.endswith("png")
        assert r.status == 200 and r.headers["content-type"].startswith("image/png" if png else "image/svg+xml"), href
        assert r.body().startswith(b"\x89PNG\r\n\x1a\n") if png else b"<svg" in r.body()[:2000], href
    page.screenshot(path=screenshots / "campaign.png", full_page=True)


def test_episode_player_slider_play_and_keyboard(watched, api, done_campaign, screenshots):
    cid = done_campaign["id"]
    trace = api.get(f"/campaigns/{cid}/tests/2/ra2vipas").json()
    w = watched()
    page = w.page
    page.goto(f"/ui/campaigns/{cid}")
    page.locator("#tests-table a[href$='/tests/2/ra2vipas']").click()
    page.wait_for_url(re.compile(r"/tests/2/ra2vipas$"))
    slider, readout, fov = page.locator("#step-slider"), page.locator("#step-readout"), page.locator("#polar .fov")
    last = len(trace["steps"]) - 1
    assert f"(step {last})" in readout.inner_text()
    assert len(page.locator("#polar .target").all()) == len(trace["targets"])
    assert page.locator("#polar .target.tx").count() == 1
    # the keyboard moves the slider: the readout and the field of view follow
    slider.focus()
    page.keyboard.press("Home")
    assert "(step 0)" in readout.inner_text()
    step0 = trace["steps"][0]
    assert f"î = {step0['i_hat']}" in readout.inner_text()
    fov0 = fov.get_attribute("d")
    page.keyboard.press("ArrowRight")
    page.keyboard.press("ArrowRight")
    assert "(step 2)" in readout.inner_text()
    if trace["steps"][2]["pan_rad"] != step0["pan_rad"]:
        assert fov.get_attribute("d") != fov0
    # play from step 0 advances by itself
    page.locator("#play").focus()
    page.keyboard.press("Enter")
    wait_until(lambda: int(slider.input_value()) >= 6, 20, what="the player advanced")
    page.locator("#play").click()  # pause
    assert page.locator("#error-chart canvas").count() == 1 and page.locator("#reward-chart canvas").count() == 1
    page.screenshot(path=screenshots / "episode.png", full_page=True)


def test_a_campaign_appears_on_home_live_runs_on_the_rigs_page_then_is_cancelled_and_deleted(watched, api, screenshots):
    """Started through the API while the home page is open: its row appears and progresses
    without a reload; the rigs page shows episodes running, then idle rigs once it is cancelled
    from its page (reached from its row)."""
    w = watched()
    page = w.page
    page.on("dialog", lambda d: d.accept())
    page.goto("/")
    page.evaluate("window.__marker = 'same page'")
    # every progress text any campaign row shows, from the row's first rendering on
    page.evaluate("""() => {
        window.__progress = [];
        const note = () => document.querySelectorAll('#campaign-rows tr[id^="campaign-"]').forEach(row => {
            const m = row.innerText.match(/(\\d+)\\/(\\d+)/);
            if (m) window.__progress.push([row.id, row.dataset.status, +m[1], +m[2]]);
        });
        new MutationObserver(note).observe(document.body, {subtree: true, childList: true, characterData: true, attributes: true});
    }""")
    # realtime: the rigs spend their time waiting for T_RF rather than computing, and it runs for minutes
    r = api.post("/campaigns", json={"tests": 400, "seed": 9, "name": "to cancel", "mode": "realtime", "overrides": {"steps": 10}})
    assert r.status_code == 201
    cid = r.json()["id"]
    row = page.locator(f"#campaign-{cid}")
    row.wait_for()

    def progressed():
        seen = {(status, done) for rid, status, done, _ in page.evaluate("window.__progress") if rid == f"campaign-{cid}"}
        return len(seen) >= 3 and any(status == "running" and done > 0 for status, done in seen)

    wait_until(progressed, 120, every=0.1, what="the campaign's row progressing live")
    assert page.evaluate("window.__marker") == "same page"
    page.screenshot(path=screenshots / "home-live.png", full_page=True)
    rigs = watched().page
    rigs.goto("/ui/rigs")
    rigs.locator('#rigs-table tbody tr[data-state="running"]').first.wait_for()
    assert "episode running" in rigs.locator('#rigs-table tbody tr[data-state="running"]').first.inner_text()
    rigs.screenshot(path=screenshots / "rigs-running.png", full_page=True)

    row.get_by_role("link", name="to cancel").click()
    page.wait_for_url(re.compile(rf"/ui/campaigns/{cid}$"))
    page.wait_for_function("() => document.querySelector('#status').textContent === 'running'", timeout=120_000)
    page.click("#cancel-button")
    enter_token(page)  # a new tab: asked again
    page.wait_for_function("() => document.querySelector('#status').textContent === 'cancelled'")
    page.locator("#delete-button").wait_for()  # the finished page swapped in: delete is offered now
    assert api.get(f"/campaigns/{cid}").json()["status"] == "cancelled"
    page.screenshot(path=screenshots / "campaign-cancelled.png", full_page=True)
    # the rigs page, still open, follows: no episode in flight any more
    rigs.wait_for_function("() => [...document.querySelectorAll('#rigs-table tbody tr')].map(r => r.dataset.state).join() === 'idle,idle'")
    page.click("#delete-button")
    page.wait_for_url(re.compile(r"/$"))
    assert api.get(f"/campaigns/{cid}").status_code == 404


def test_a_wrong_token_is_asked_again_and_changes_nothing(watched, api, done_campaign):
    r = api.post("/campaigns", json={"overrides": SMALL, "tests": 2, "algorithms": ["rapas"], "name": "wrong token"})
    cid = r.json()["id"]
    wait_done(api, cid)
    w = watched(expect=(401,))
    page = w.page
    page.on("dialog", lambda d: d.accept())
    page.goto(f"/ui/campaigns/{cid}")
    page.click("#delete-button")
    page.fill("#token-input", "not-the-token")
    page.click("#token-form button[type=submit]")
    page.locator("#token-error").wait_for(state="visible")
    assert "refused" in page.locator("#token-error").inner_text()
    page.click("#token-cancel")
    assert api.get(f"/campaigns/{cid}").status_code == 200
    assert page.evaluate("sessionStorage.getItem('ra2vipas.apiToken')") is None  # a refused token is not kept


def test_rigs_page_shows_the_live_rigs_and_learner(watched, screenshots):
    w = watched()
    w.page.goto("/ui/rigs")
    rows = w.page.locator("#rigs-table tbody tr")
    rows.first.wait_for()
    text = w.page.locator("#rigs").inner_text()
    assert "rig-1" in text and "rig-2" in text and "live since" in text and "learner" in text
    # no campaign is running: both rigs idle, their sensors and controllers up
    w.page.wait_for_function("() => [...document.querySelectorAll('#rigs-table tbody tr')].map(r => r.dataset.state).join() === 'idle,idle'")
    for name in ("rig-1", "rig-2"):
        cells = w.page.locator(f'#rigs-table tr[data-rig="{name}"] td').all_inner_texts()
        assert cells[:4] == ["idle", "up", "up", "0"], cells
    w.page.screenshot(path=screenshots / "rigs.png", full_page=True)


@pytest.mark.parametrize("path", ["/", "/ui/new", "/ui/rigs", "CAMPAIGN", "EPISODE"])
def test_pages_fit_a_phone_and_tab_order_starts_with_the_skip_link(watched, done_campaign, screenshots, path):
    cid = done_campaign["id"]
    url = {"CAMPAIGN": f"/ui/campaigns/{cid}", "EPISODE": f"/ui/campaigns/{cid}/tests/0/ra2vipas"}.get(path, path)
    w = watched(viewport=PHONE)
    page = w.page
    page.goto(url)
    page.wait_for_load_state("networkidle") if path not in ("/", "/ui/rigs") else page.wait_for_timeout(500)
    # nothing wider than the screen: wide tables scroll inside their own box
    assert page.evaluate("document.documentElement.scrollWidth") <= PHONE["width"]
    page.keyboard.press("Tab")
    assert page.evaluate("document.activeElement.textContent") == "Skip to content"
    page.keyboard.press("Enter")
    page.keyboard.press("Tab")
    assert page.evaluate("document.activeElement.closest('main') !== null")
    name = {"/": "home", "/ui/new": "new", "/ui/rigs": "rigs"}.get(path, path.lower())
    page.screenshot(path=screenshots / f"phone-{name}.png", full_page=True)


def wait_study(api, sid: str, timeout: float = 180.0) -> dict:
    return wait_until(lambda: (s := api.get(f"/studies/{sid}").json())["status"] in ("done", "failed", "cancelled") and s,
                      timeout, what=f"study {sid} finished")


def test_a_study_appears_and_progresses_live_then_its_page_plots_it_and_links_its_points(watched, api, screenshots):
    w = watched()
    page = w.page
    page.goto("/")
    page.get_by_role("link", name="Studies").click()  # the navigation's link
    page.wait_for_url(re.compile(r"/ui/studies$"))
    page.evaluate("window.__marker = 'same page'")
    # every progress text any study row shows, from the first rendering of the row on (polling the row
    # from here could miss a fast study's intermediate states: a rig on an idle machine runs it in ~1 s)
    page.evaluate("""() => {
        window.__progress = [];
        const note = () => document.querySelectorAll('[id^="study-"]').forEach(row => {
            const m = row.innerText.match(/\\d+\\/\\d+/);
            if (m) window.__progress.push([row.id, m[0]]);
        });
        new MutationObserver(note).observe(document.body, {subtree: true, childList: true, characterData: true, attributes: true});
    }""")
    # started through the API while the page is open: its row appears, progresses and finishes without a reload
    r = api.post("/studies", json={"overrides": {"steps": 100, "n_train": 250}, "vary": {"n_targets": [6, 12]},
                                   "algorithms": ["ra2vipas", "rapas"], "tests": 24, "seed": 2, "name": "browser study"})
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    row = page.locator(f"#study-{sid}")
    row.wait_for()
    assert "browser study" in row.inner_text() and "n_targets" in row.inner_text()
    wait_until(lambda: row.get_attribute("data-status") == "done", 180, every=0.1, what="the study's row shows it done")
    seen = {text for rid, text in page.evaluate("window.__progress") if rid == f"study-{sid}"}
    assert len(seen) >= 2 and "96/96" in seen, seen  # 2 points x 24 tests x 2 algorithms, updated live (a tick is 0.5 s)
    assert page.evaluate("window.__marker") == "same page"
    page.screenshot(path=screenshots / "studies.png", full_page=True)

    # the study page: one line per algorithm over n_targets, the legend with the API's values, the points
    results = api.get(f"/studies/{sid}/results").json()
    row.get_by_role("link", name="browser study").click()
    page.wait_for_url(re.compile(rf"/ui/studies/{sid}$"))
    page.locator("#study-chart canvas").wait_for()
    legend = " ".join(page.locator("#study-legend").inner_text().split())
    last = {r["algorithm"]: r for r in results["rows"] if r["n_targets"] == 12}
    assert f"Ra²ViPAS {last['ra2vipas']['dr_final']:.3f}" in legend and f"RaPAS {last['rapas']['dr_final']:.3f}" in legend
    assert "n_targets=12, n=24" in legend
    before = page.locator("#study-chart canvas").evaluate("c => c.toDataURL()")
    page.select_option("#metric", "time_to_dr90_s")  # another metric: redrawn, its figure exported
    page.wait_for_function("() => document.querySelector('#export-png').href.includes('/plots/time_to_dr90_s')")
    assert page.locator("#study-chart canvas").evaluate("c => c.toDataURL()") != before
    assert page.request.get(page.locator("#export-png").get_attribute("href")).status == 200
    assert page.locator("#points-table tbody").count() == 2
    page.screenshot(path=screenshots / "study.png", full_page=True)

    # a point's link opens its campaign page, which links back to the study
    point = api.get(f"/studies/{sid}").json()["points"][1]
    page.locator("#point-1 a").first.click()
    page.wait_for_url(re.compile(rf"/ui/campaigns/{point['campaign_id']}$"))
    page.locator("#dr-chart canvas").wait_for()
    point_results = api.get(f"/campaigns/{point['campaign_id']}/results").json()
    if point_results["algorithms"]["ra2vipas"].get("calibration", {}).get("reliability"):
        page.locator("#reliability-chart canvas").wait_for()  # the reliability diagram beside the summary
        assert "ECE" in page.locator("#reliability-legend").inner_text()
    page.screenshot(path=screenshots / "study-point-campaign.png", full_page=True)
    page.locator("#study-link").click()
    page.wait_for_url(re.compile(rf"/ui/studies/{sid}$"))


def test_cancel_a_study_from_its_page_then_delete_it(watched, api, screenshots):
    r = api.post("/studies", json={"vary": {"n_targets": [10, 20]}, "tests": 300, "seed": 3, "name": "study to cancel"})
    assert r.status_code == 201
    sid = r.json()["id"]
    w = watched()
    page = w.page
    page.on("dialog", lambda d: d.accept())
    page.goto(f"/ui/studies/{sid}")
    page.click("#cancel-button")
    enter_token(page)
    page.wait_for_function("() => document.querySelector('#status').textContent === 'cancelled'")
    page.locator("#delete-button").wait_for()  # the finished page swapped in
    assert api.get(f"/studies/{sid}").json()["status"] == "cancelled"
    page.click("#delete-button")
    page.wait_for_url(re.compile(r"/ui/studies$"))
    assert api.get(f"/studies/{sid}").status_code == 404


@pytest.fixture(scope="module")
def done_study(api):
    r = api.post("/studies", json={"overrides": {"steps": 30, "n_train": 250},
                                   "vary": {"n_targets": [6, 10]}, "algorithms": ["rapas"], "tests": 2, "seed": 1, "name": "phone"})
    assert r.status_code == 201, r.text
    s = wait_study(api, r.json()["id"])
    assert s["status"] == "done"
    return s


@pytest.mark.parametrize("path", ["/ui/studies", "STUDY"])
def test_studies_pages_fit_a_phone(watched, done_study, screenshots, path):
    w = watched(viewport=PHONE)
    page = w.page
    page.goto(path if path != "STUDY" else f"/ui/studies/{done_study['id']}")
    if path == "STUDY":
        page.locator("#study-chart canvas").wait_for()
    else:
        page.locator(f"#study-{done_study['id']}").wait_for()
    assert page.evaluate("document.documentElement.scrollWidth") <= PHONE["width"]
    page.keyboard.press("Tab")
    assert page.evaluate("document.activeElement.textContent") == "Skip to content"
    page.screenshot(path=screenshots / f"phone-{'study' if path == 'STUDY' else 'studies'}.png", full_page=True)


def test_no_token_in_the_stack_logs(stack, screenshots):
    """The browser sent the token in headers only; no service wrote it anywhere."""
    for log in stack["logs"].rglob("*"):
        if log.is_file():
            assert TOKEN not in log.read_text(errors="replace"), log
