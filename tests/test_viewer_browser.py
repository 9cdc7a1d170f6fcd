"""The viewer in a real browser: Debian's headless chromium driven by Playwright.

The app serves the hand-made box workspace of test_viewer_api (three pieces,
assembled, plus an unassembled case) from a thread on a free port. Checked: the
canvas shows the fragments (a real share of non-background pixels, in the
fragments' own colours), one list row per fragment, the scattered/assembled
toggle changes the picture, contours arrive, picking two contour points re-runs
the match with those head nodes, a match row shows its pair alone, an assembly
started from the page streams its progress and reloads the case, and the
console shows no errors. Skipped only when /usr/bin/chromium is absent.

Set RELICGPU_SCREENSHOT_DIR to keep the screenshots.
"""
from __future__ import annotations

import colorsys
import io
import json
import os
from pathlib import Path

import numpy as np
import pytest

CHROMIUM = Path("/usr/bin/chromium")
pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian's chromium is not installed (apt-get install chromium)"),
]

# Software WebGL (SwiftShader through ANGLE): there is no GPU in CI.
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
BACKGROUND = (0x1D, 0x21, 0x27)  # viewer/scene.js BACKGROUND
GOLDEN = 0.381966  # viewer/scene.js fragmentColor: hue = (0.03 + i * GOLDEN) % 1
TIMEOUT_MS = 30_000


def fragment_hue(i: int) -> float:
    return (0.03 + i * GOLDEN) % 1


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    pytest.importorskip("playwright")
    from relicgpu.viewer.app import create_app, serve_in_thread, viewer_dir
    from test_viewer_api import TruthPipeline, make_box_workspace

    if not (viewer_dir() / "node_modules" / "three" / "build" / "three.module.js").is_file():
        pytest.fail("three.js is not installed: run `npm ci` in viewer/ (CI must do this)")
    ws = tmp_path_factory.mktemp("ws")
    truth = make_box_workspace(ws)
    other = make_box_workspace(ws, case="other", seed=1, assembled=False)
    pipe = TruthPipeline(truth)
    other_pipe = TruthPipeline(other)

    def prepare(fragment, scale):  # both cases have piece_0..2: the truth of the case the file came from
        src = Path(fragment.source or "")
        return (other_pipe if "other" in src.parts else pipe).prepare(fragment, scale)

    def assemble(frag_dir, out_dir, report):
        # The known poses of the unassembled case, written as relicgpu.assemble would.
        names = other["names"]
        for i, _ in enumerate(names):
            report(stage="pairs", done=i + 1, total=len(names))
        doc = {"version": 1, "fragments": [{"file": f"{n}.ply", "pose": other["poses"][n].tolist(), "group": 0}
                                            for n in names],
               "matches": [{"a": names[0], "b": names[1],
                            "transform": (np.linalg.inv(other["poses"][names[0]]) @ other["poses"][names[1]]).tolist(),
                            "score": 0.8, "rmse": 0.001, "overlap": 0.7, "used": True}],
               "backend": "numpy", "engine": "local", "timings": {}}
        from relicgpu.io.files import atomic_write_json
        atomic_write_json(out_dir / "assembly.json", doc)
        return {"fragments": 3, "placed": 3, "groups": 1}

    app = create_app(ws, prepare=prepare, match_pair=pipe.match_pair, assemble=assemble)
    server, url = serve_in_thread(app)
    yield url, truth, pipe
    server.close()


@pytest.fixture(scope="module")
def browser():
    pytest.importorskip("playwright")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        # launch() gives every run a fresh temporary user-data dir.
        b = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        yield b
        b.close()


def new_page(browser):
    """A page that records console errors, page errors and failed requests in .problems."""
    pg = browser.new_page(viewport={"width": 1280, "height": 800})
    pg.set_default_timeout(TIMEOUT_MS)
    problems: list[str] = []
    pg.on("console", lambda m: problems.append(f"console.{m.type}: {m.text}") if m.type == "error" else None)
    pg.on("pageerror", lambda e: problems.append(f"page error: {e}"))
    # The page closes its event stream on the final state, which may abort the tail of that
    # response: expected. Any other failed request is a problem.
    pg.on("requestfailed", lambda r: None if ("/api/progress" in r.url and "ERR_ABORTED" in (r.failure or ""))
          else problems.append(f"request failed: {r.url} {r.failure}"))
    pg.problems = problems
    return pg


@pytest.fixture(scope="module")
def page(served, browser):
    pg = new_page(browser)
    pg.goto(served[0])
    pg.wait_for_selector('body[data-state="ready"]')
    yield pg
    pg.close()


def shot(page, name: str):
    """The canvas as an (H, W, 3) uint8 array; saved when RELICGPU_SCREENSHOT_DIR is set."""
    from PIL import Image

    png = page.locator("#canvas-host canvas").screenshot()
    out = os.environ.get("RELICGPU_SCREENSHOT_DIR")
    if out:
        Path(out).mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(Path(out) / f"{name}.png"))
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


def colour_shares(img: np.ndarray, n_fragments: int) -> tuple[float, list[float]]:
    """Share of non-background pixels, and per fragment the share of pixels of its hue."""
    px = img.reshape(-1, 3).astype(int)
    fg = np.abs(px - np.array(BACKGROUND)).max(axis=1) > 16
    hsv = np.array([colorsys.rgb_to_hsv(*(c / 255.0)) for c in px[fg][::7]])  # every 7th: plenty, quick
    shares = []
    for i in range(n_fragments):
        d = np.abs(hsv[:, 0] - fragment_hue(i))
        d = np.minimum(d, 1 - d)
        own = (d < 0.035) & (hsv[:, 1] > 0.3) & (hsv[:, 2] > 0.12)
        shares.append(float(own.sum() * 7 / len(px)))
    return float(fg.mean()), shares


def visible_contour_point(page, name: str):
    """Screen position of a contour point of `name` that a click there would pick (not hidden)."""
    return page.evaluate("""(name) => {
        const v = window.relicViewer.view;
        const rec = v.fragments.get(name);
        for (let ci = 0; ci < rec.contours.length; ci++) {
          for (let pi = 0; pi < rec.contours[ci].points.length; pi += 3) {
            const s = v.screenPositionOf(name, ci, pi);
            const hit = v.pickContourPoint(s.x, s.y, 4);
            if (hit && hit.name === name) return s;
          }
        }
        return null; }""", name)


def test_scene_list_toggle_and_console(page, served):
    _, truth, _ = served
    names = truth["names"]
    rows = page.locator("#fragment-list li")
    assert rows.count() == len(names)
    assert [rows.nth(i).get_attribute("data-name") for i in range(rows.count())] == names
    page.wait_for_selector('body[data-contours="ready"]')

    assembled = shot(page, "assembled")
    fg, shares = colour_shares(assembled, len(names))
    assert fg > 0.08, f"only {fg:.1%} of the canvas shows anything"
    coloured = [s for s in shares if s > 0.005]
    assert len(coloured) >= 2, f"fragment colour shares {shares}"

    page.click("#toggle-btn")
    page.wait_for_selector('body[data-anim="idle"]')
    scattered = shot(page, "scattered")
    changed = (np.abs(scattered.astype(int) - assembled.astype(int)).max(axis=2) > 24).mean()
    assert changed > 0.03, f"the toggle changed only {changed:.1%} of the pixels"
    fg2, shares2 = colour_shares(scattered, len(names))
    assert fg2 > 0.02 and sum(s > 0.002 for s in shares2) >= 2, (fg2, shares2)

    page.click("#toggle-btn")  # back to assembled
    page.wait_for_selector('body[data-anim="idle"]')
    back = shot(page, "assembled-again")
    assert (np.abs(back.astype(int) - assembled.astype(int)).max(axis=2) > 24).mean() < changed / 3
    assert page.problems == []


def fracture_tone_share(img: np.ndarray) -> float:
    """Share of pixels in the pale, greyish tone fracture faces are shaded with."""
    px = img.reshape(-1, 3).astype(float) / 255
    mx, mn = px.max(axis=1), px.min(axis=1)
    sat = np.where(mx > 0, (mx - mn) / np.maximum(mx, 1e-9), 0)
    return float(((sat < 0.28) & (mx > 0.35)).mean())


def test_exploded_view_shows_fracture_faces_shaded_apart(page):
    page.wait_for_selector('body[data-contours="ready"]')
    closed = fracture_tone_share(shot(page, "closed"))
    page.locator("#explode-slider").fill("1000")
    exploded = shot(page, "exploded")
    shaded = fracture_tone_share(exploded)
    page.uncheck("#fracture-check")
    plain = fracture_tone_share(shot(page, "exploded-no-fracture-shading"))
    page.check("#fracture-check")
    page.locator("#explode-slider").fill("0")
    page.click("#fit-btn")
    # the cut faces inside the box come into view, in their own tone, which goes when shading is off
    assert shaded > 0.01 and shaded > 5 * max(plain, closed, 1e-4), (closed, shaded, plain)
    assert page.problems == []


def test_pick_head_nodes_rematches_the_pair(page, served):
    _, truth, pipe = served
    page.wait_for_selector('body[data-contours="ready"]')
    page.click("#toggle-btn")  # scattered: the pieces apart, contours easy to click
    page.wait_for_selector('body[data-anim="idle"]')
    page.click("#pick-btn")
    a = visible_contour_point(page, "piece_0")
    b = visible_contour_point(page, "piece_1")
    assert a and b, "no visible contour point to click"
    calls_before = len(pipe.match_calls)
    page.mouse.click(a["x"], a["y"])
    page.mouse.click(b["x"], b["y"])
    page.wait_for_selector('body[data-match="done"]')
    picks = page.evaluate("window.relicViewer.state.picks.map(p => [p.name, p.contour, p.point])")
    assert [p[0] for p in picks] == ["piece_0", "piece_1"]
    assert pipe.match_calls[calls_before:] == [("piece_0", "piece_1", (picks[0][1], picks[0][2], picks[1][1], picks[1][2]))]
    assert "accepted" in page.inner_text("#match-result")
    shown = page.evaluate("window.relicViewer.view.shownRecords().map(r => r.name)")
    assert sorted(shown) == ["piece_0", "piece_1"]
    shot(page, "hand-match")
    page.click("#show-all-btn")
    page.click("#pick-btn")
    assert len(page.evaluate("window.relicViewer.view.shownRecords()")) == 3
    assert page.problems == []


def test_match_row_shows_the_pair_alone(page):
    page.wait_for_selector('body[data-matches="ready"]')
    rows = page.locator("#match-list li")
    assert rows.count() == 3
    rows.nth(0).click()
    shown = page.evaluate("window.relicViewer.view.shownRecords().map(r => r.name)")
    assert sorted(shown) == ["piece_0", "piece_1"]  # the best used match
    assert "score" in page.inner_text("#match-result")
    page.click("#show-all-btn")
    assert page.problems == []


def test_hide_and_focus_from_the_list(page):
    row = page.locator('#fragment-list li[data-name="piece_2"]')
    row.locator("input").uncheck()
    assert "piece_2" not in page.evaluate("window.relicViewer.view.shownRecords().map(r => r.name)")
    row.locator("input").check()
    row.locator(".name").click()
    assert "active" in row.get_attribute("class")
    assert page.problems == []


def test_assemble_from_the_page_streams_progress(page):
    page.select_option("#case-select", "other")
    page.wait_for_function("document.body.dataset.state === 'ready' && window.relicViewer.state.caseId === 'other'")
    assert page.is_disabled("#toggle-btn")  # not assembled yet
    page.click("#assemble-btn")
    page.wait_for_selector('body[data-job="done"]')
    page.wait_for_function("document.body.dataset.state === 'ready' && window.relicViewer.state.info.assembled")
    assert "assembled in" in page.inner_text("#job-status")
    assert not page.is_disabled("#toggle-btn")
    # the match list is filled after the case shows 'ready' (loadMatches): wait for it
    page.wait_for_selector('body[data-matches="ready"]')
    assert page.locator("#match-list li").count() == 1
    assert page.problems == []


def test_demo_case_end_to_end(browser, tmp_path, monkeypatch):
    """`relicgpu demo`'s case (relicgpu.synth + relicgpu.assemble, the real pipeline) in the browser."""
    import importlib.util

    if importlib.util.find_spec("relicgpu.synth") is None or importlib.util.find_spec("relicgpu.heap.assembly") is None:
        pytest.skip("relicgpu.synth and relicgpu.heap.assembly are not installed yet")
    from relicgpu.demo import make_case
    from relicgpu.viewer.app import create_app, serve_in_thread

    monkeypatch.setenv("RELICGPU_BACKEND", "numpy")  # no kernel compilation in a quick test
    case = make_case(tmp_path, shape="vase", pieces=3, seed=1, log=lambda msg: None)
    doc = json.loads((case / "assembly" / "assembly.json").read_text())
    placed = sum(f["pose"] is not None for f in doc["fragments"])
    server, url = serve_in_thread(create_app(tmp_path))
    try:
        pg = new_page(browser)
        pg.set_default_timeout(60_000)
        pg.goto(f"{url}#case={case.name}")
        pg.wait_for_selector('body[data-state="ready"]')
        assert pg.locator("#fragment-list li").count() == len(doc["fragments"]) == 3
        pg.wait_for_selector('body[data-contours="ready"]')
        first = shot(pg, "demo")
        fg, shares = colour_shares(first, 3)
        # (scattered pieces, when nothing is placed, are small in a view that holds them all)
        assert fg > 0.004 and sum(s > 0.0005 for s in shares) >= 2, (fg, shares)
        if placed >= 2:
            pg.click("#toggle-btn")
            pg.wait_for_selector('body[data-anim="idle"]')
            changed = (np.abs(shot(pg, "demo-scattered").astype(int) - first.astype(int)).max(axis=2) > 24).mean()
            assert changed > 0.01
        assert pg.problems == []
        pg.close()
    finally:
        server.close()


def _serve_box(tmp_path, case, groups=None):
    """The three-piece box of test_viewer_api as case `case` (with `groups` as its groups.json),
    served: (truth, server, url)."""
    pytest.importorskip("playwright")
    from relicgpu.viewer.app import create_app, serve_in_thread
    from test_viewer_api import TruthPipeline, make_box_workspace

    truth = make_box_workspace(tmp_path / "ws", case=case)
    if groups is not None:
        (tmp_path / "ws" / case / "groups.json").write_text(json.dumps(groups))
    pipe = TruthPipeline(truth)
    server, url = serve_in_thread(create_app(tmp_path / "ws", prepare=pipe.prepare, match_pair=pipe.match_pair))
    return truth, server, url


def test_object_groups_colour_and_list_the_fragments(browser, tmp_path):
    """A case with a groups.json (`relicgpu group`): fragments coloured by object group, a legend
    of the groups, each list row tagged with its object; 'colour by fragment' brings the fragment
    colours back."""
    objects = {"piece_0": 0, "piece_1": 1, "piece_2": 0}
    _, server, url = _serve_box(tmp_path, "heap", groups={
        "version": 1, "method": "average", "fragments": [{"file": f"{n}.ply", "group": g} for n, g in objects.items()]})
    try:
        pg = new_page(browser)
        pg.goto(url)
        pg.wait_for_selector('body[data-state="ready"][data-colour="object"]')
        assert pg.locator("#colour-select").input_value() == "object"
        legend = pg.locator("#group-legend span")
        assert [legend.nth(i).inner_text() for i in range(legend.count())] == ["object 0 (2)", "object 1 (1)"]
        tags = {n: pg.locator(f'#fragment-list li[data-name="{n}"] .tag').inner_text() for n in objects}
        assert all(tags[n].startswith(f"object {g}") for n, g in objects.items()), tags
        swatch = {n: pg.locator(f'#fragment-list li[data-name="{n}"] .swatch').evaluate(
            "e => getComputedStyle(e).backgroundColor") for n in objects}
        assert swatch["piece_0"] == swatch["piece_2"] != swatch["piece_1"]
        assert "2 object groups" in pg.locator("#case-status").inner_text()
        # group g has fragment g's hue: by object, no pixel has fragment 2's own hue
        _, by_object = colour_shares(shot(pg, "by-object"), 3)
        assert by_object[0] > 0.005 and by_object[1] > 0.002 and by_object[2] < 0.0005, by_object
        pg.select_option("#colour-select", "fragment")
        pg.wait_for_selector('body[data-colour="fragment"]')
        _, by_fragment = colour_shares(shot(pg, "by-fragment"), 3)
        assert by_fragment[2] > 0.002, by_fragment
        assert pg.locator("#group-legend span").count() == 0
        assert pg.problems == []
        pg.close()
    finally:
        server.close()


def test_colour_by_how_each_piece_is_held(browser, tmp_path):
    """'how it is held' colours an assembled case by support (relicgpu.heap.support): the box's
    three pieces joined by a chain of two used matches, so the middle one is in a chain and the two
    ends rest on one match each, tagged so in the list; with the third match used they all lie on a loop."""
    truth, server, url = _serve_box(tmp_path, "box")
    try:
        pg = new_page(browser)
        pg.goto(url)
        pg.wait_for_selector('body[data-state="ready"]')
        pg.select_option("#colour-select", "support")
        pg.wait_for_selector('body[data-colour="support"]')
        legend = pg.locator("#group-legend span")
        assert [legend.nth(i).inner_text() for i in range(legend.count())] == [
            "in a chain of matches, no loop (1)", "rests on one match alone (2)"]
        tags = {n: pg.locator(f'#fragment-list li[data-name="{n}"] .tag').inner_text() for n in truth["names"]}
        assert tags == {"piece_0": "group 0 · one match", "piece_1": "group 0 · no loop", "piece_2": "group 0 · one match"}
        swatch = {n: pg.locator(f'#fragment-list li[data-name="{n}"] .swatch').evaluate(
            "e => getComputedStyle(e).backgroundColor") for n in truth["names"]}
        assert swatch["piece_0"] == swatch["piece_2"] != swatch["piece_1"]
        assert pg.problems == []
        pg.close()

        path = tmp_path / "ws" / "box" / "assembly" / "assembly.json"
        doc = json.loads(path.read_text())
        doc["matches"][2]["used"] = True
        path.write_text(json.dumps(doc))
        pg = new_page(browser)
        pg.goto(url)
        pg.wait_for_selector('body[data-state="ready"]')
        pg.select_option("#colour-select", "support")
        pg.wait_for_selector('body[data-colour="support"]')
        assert pg.locator("#group-legend span").all_inner_texts() == ["on a closed loop of matches (3)"]
        assert all(pg.locator(f'#fragment-list li[data-name="{n}"] .tag').inner_text() == "group 0"
                   for n in truth["names"])
        assert pg.problems == []
        pg.close()
    finally:
        server.close()
