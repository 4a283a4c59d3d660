"""The browser view of guided collection (issue 36, item 5): it follows the samples as they arrive, and a real
headless Chromium shows the scene and its update (skipped only where no browser is installed)."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from ivc.collect.guide import collect_step
from ivc.collect.rules import SweepRule
from ivc.collect.stream import SessionSource
from ivc.errors import LiveError
from ivc.session import Session
from tests.browser import Chromium, find_chromium, wait_for
from tests.live_helpers import Unlabelled

pytest.importorskip("viser")

AMBER = np.array([250, 190, 60])  # the samples' colour (ivc.collect.view)
BLUE = np.array([90, 140, 255])  # the cube's edges


def colour_count(image: np.ndarray, colour: np.ndarray, tolerance: int = 40) -> int:
    return int(np.all(np.abs(image.astype(int) - colour) < tolerance, axis=-1).sum())


@pytest.fixture(scope="module")
def sweep_statuses(small_session):
    """The statuses of a guided wand sweep (the small scene's), in the order they arrived."""
    simulator, session = small_session
    before = Session(session.hemisphere, {k: session.steps[k] for k in ("cube_calibration", "cube_survey",
                                                                        "wand_calibration")})
    rule = SweepRule(before, min_kept=10**9, per_octant=200, per_direction=20, chunk=24)
    statuses = []
    with SessionSource(Session(session.hemisphere, {"wand_sweep": session.steps["wand_sweep"]}), chunk=24) as source:
        collect_step(Unlabelled(source), "wand_sweep", rule=rule, on_status=statuses.append, status_every_s=0)
    return statuses


def test_the_view_names_its_extra_when_viser_is_missing(monkeypatch):
    from ivc.collect.view import BrowserView

    monkeypatch.setitem(sys.modules, "viser", None)
    with pytest.raises(LiveError, match=r"pip install 'ivc\[view\]'"):
        BrowserView(port=0)


def test_the_view_follows_the_samples(sweep_statuses):
    from ivc.collect.view import BrowserView

    view = BrowserView(port=0)
    try:
        assert view.url.startswith("http://127.0.0.1:")
        drawn = []
        arrived = [s for s in sweep_statuses if s.points is not None and len(s.points)]
        for status in arrived[:: max(1, len(arrived) // 5)]:
            view(status)
            drawn.append(dict(view.scene))
        assert view.updates == len(drawn)
        frames = [d["frames"] for d in drawn]
        assert frames == sorted(frames) and frames[-1] > frames[0]
        assert drawn[-1]["points"] > drawn[0]["points"] > 0
        assert len(drawn[-1]["cells"]) == 8 and sum(drawn[-1]["cells"]) > sum(drawn[0]["cells"])
        assert drawn[-1]["target"] is not None  # the rule still wants more: a thin region to go to
    finally:
        view.close()


@pytest.mark.skipif(find_chromium() is None, reason="no Chromium installed (Debian: apt-get install chromium)")
def test_a_headless_browser_shows_the_scene_and_its_update(sweep_statuses, tmp_path):
    from PIL import Image

    from ivc.collect.view import BrowserView

    first = next(s for s in sweep_statuses if s.points is not None and len(s.points) >= 100)
    last = sweep_statuses[-1]
    assert last.points.shape[0] > 5 * first.points.shape[0]
    view = BrowserView(port=0)
    try:
        view(first)
        with Chromium() as browser:
            browser.open(view.url)
            def drawn(image):
                return colour_count(image, AMBER) > 20 and colour_count(image, BLUE, 60) > 5

            (before,) = wait_for(lambda: (lambda image: (image,) if drawn(image) else None)(browser.screenshot()),
                                 "the samples and the cube drawn", deadline_s=180)
            Image.fromarray(before).save(tmp_path / "first.png")
            assert before.std() > 10  # not a blank page
            counted = colour_count(before, AMBER)
            view(last)  # more samples arrive
            (after,) = wait_for(lambda: (lambda image: (image,) if colour_count(image, AMBER) > 2 * counted else None)(
                browser.screenshot()), "the new samples drawn", deadline_s=180)
            Image.fromarray(after).save(tmp_path / "second.png")
        assert np.mean(np.any(after != before, axis=-1)) > 0.01
        assert view.updates == 2
    finally:
        view.close()
