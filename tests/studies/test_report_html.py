"""report.html: the report as one self-contained page — its tables, every figure inlined byte for byte, nothing
outside the file, plotly.js once with a div per interactive chart, and a full page without plotly."""

import base64
import sys
from html.parser import HTMLParser
from pathlib import Path

import pytest
from PIL import Image

from magctl.studies.report_html import write_html_report
from magctl.studies.runner import Cause, PaperRow, StudyResult, claim

SUMMARIES = {
    "K_c=0, δ(0)=0": {"converged_by_attempt": [0.1, 0.5, 0.9], "mean_error_um_by_attempt": [600.0, 310.0, 90.0, 40.0],
                      "std_error_um_by_attempt": [0.0, 45.0, 20.0, 8.0], "attempts_all": [1, 2, 3, 3, 2]},
    "K_c=1, δ(0)=151 µm": {"converged_by_attempt": [0.7, 1.0, 1.0], "mean_error_um_by_attempt": [600.0, 70.0, 20.0,
                                                                                                 20.0],
                           "std_error_um_by_attempt": [0.0, 30.0, 4.0, 4.0], "attempts_all": [1, 1, 2, 1, 1]},
}
POINTS = [{"gap_um": 250.0, "displacement_um": 480.0, "along_um": 3.0, "contact": True},
          {"gap_um": 400.0, "displacement_um": 61.5, "along_um": 1.0, "contact": False},
          {"gap_um": 650.0, "displacement_um": 12.25, "along_um": 0.5, "contact": False}]


class Page(HTMLParser):
    """Every tag with its attributes, the table cells' text and the scripts' text."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.tags, self.cells, self.scripts, self.text = [], [], [], []
        self._cell = self._script = None

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))
        if tag in ("td", "th"):
            self._cell = []
        elif tag == "script":
            self._script = []

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._cell is not None:
            self.cells.append("".join(self._cell).strip())
            self._cell = None
        elif tag == "script" and self._script is not None:
            self.scripts.append("".join(self._script))
            self._script = None

    def handle_data(self, data):
        self.text.append(data)
        if self._cell is not None:
            self._cell.append(data)
        if self._script is not None:
            self._script.append(data)

    def attrs(self, tag):
        return [a for t, a in self.tags if t == tag]


def parse(path: Path) -> Page:
    page = Page()
    page.feed(path.read_text(encoding="utf-8"))
    page.close()
    return page


@pytest.fixture
def results(tmp_path):
    """Two studies by hand: a push study with a PNG, a two-frame GIF and controller summaries, and a side-push
    curve; one claim and one plain quantity."""
    folder = tmp_path / "front-push"
    folder.mkdir()
    png, gif = folder / "fig10.png", folder / "push.gif"
    Image.new("RGB", (6, 4), (200, 30, 30)).save(png)
    frames = [Image.new("RGB", (5, 5), colour) for colour in ((255, 0, 0), (0, 0, 255))]
    frames[0].save(gif, save_all=True, append_images=frames[1:], duration=100, loop=0)
    with Image.open(gif) as im:
        assert im.n_frames == 2                                   # the fixture really is an animation
    rows = [claim("§VI-A", "front claim", "yes", "no", "closed loop", holds=False,
                  cause=Cause("release 151 µm off.", True)),
            PaperRow("release displacement", "127 µm", "151 µm", model="fluid model", note="paper's set-up")]
    return [StudyResult("front-push", {"controllers": SUMMARIES, "trials_per_controller": 5}, [png, gif],
                        ["Six controllers, five trials each.", "| controller | converged |", "|---|---|",
                         "| K_c=1 | 100 % |"], rows),
            StudyResult("sidepush-curve", {"points": POINTS, "fit": {"a_um": 1.0}}, [], ["The curve."], [])]


def test_tables_sections_and_contents_are_there(tmp_path, results):
    path = write_html_report(tmp_path, results, {"front-push": 2.5, "sidepush-curve": 1.0})
    assert path == tmp_path / "report.html"
    page = parse(path)
    cells = page.cells
    for cell in ("§VI-A", "front claim", "closed loop", "not reproduced", "release 151 µm off.",   # claims table
                 "release displacement", "127 µm", "151 µm", "fluid model", "paper's set-up",     # quantities
                 "controller", "K_c=1", "100 %"):                                                   # a summary's table
        assert cell in cells, cell
    ids = {a.get("id") for _, a in page.tags}
    links = [a["href"] for a in page.attrs("a") if "href" in a]
    for section in ("claims", "quantities", "study-front-push", "study-sidepush-curve"):
        assert section in ids and f"#{section}" in links, section
    text = " ".join(page.text)
    assert "Six controllers, five trials each." in text and "wall time 2.5 s" in text and "The curve." in text


def test_every_figure_is_inlined_byte_for_byte_and_nothing_points_outside(tmp_path, results):
    page = parse(write_html_report(tmp_path, results, {}))
    images = page.attrs("img")
    assert len(images) == 2
    for img, source in zip(images, results[0].figures, strict=True):
        head, payload = img["src"].split(",", 1)
        assert head == {"fig10.png": "data:image/png;base64", "push.gif": "data:image/gif;base64"}[source.name]
        assert base64.b64decode(payload) == source.read_bytes()
    for tag, attrs in page.tags:
        for key in ("src", "href"):
            if key in attrs:
                value = attrs[key]
                assert value.startswith(("data:", "#")), (tag, key, value[:80])
                assert "http:" not in value and "https:" not in value


def test_interactive_charts_with_plotly_js_once(tmp_path, results):
    pytest.importorskip("plotly")
    from plotly.offline import get_plotlyjs

    page = parse(write_html_report(tmp_path, results, {}))
    source = get_plotlyjs()
    html = (tmp_path / "report.html").read_text(encoding="utf-8")
    assert html.count(source[:2000]) == 1 and html.count(source[-2000:]) == 1
    assert sum(source in s for s in page.scripts) == 1
    assert not any(a.get("src") for a in page.attrs("script"))          # no script loaded from anywhere
    ids = {a.get("id") for _, a in page.tags}
    for chart in ("plot-front-push-converged", "plot-front-push-errors", "plot-front-push-attempts",
                  "plot-sidepush-curve-curve"):
        assert chart in ids, chart
        assert sum("Plotly.newPlot(" in s and f'"{chart}"' in s for s in page.scripts) == 1, chart
    # the charts carry the studies' numbers: the converged shares in %, the attempts, the curve's points
    plots = "".join(s for s in page.scripts if source not in s)
    assert "[10.0,50.0,90.0]" in plots and "[1,2,3,3,2]" in plots and "[0.0,45.0,20.0,8.0]" in plots
    assert "[61.5,12.25]" in plots and "[480.0]" in plots                # contact and no contact, one trace each
    assert "pip install" not in " ".join(page.text)


def test_without_plotly_the_page_is_complete_and_says_how_to_get_the_charts(tmp_path, results, monkeypatch):
    for name in [m for m in sys.modules if m == "plotly" or m.startswith("plotly.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "plotly", None)                  # import plotly now raises ImportError
    page = parse(write_html_report(tmp_path, results, {}))
    text = " ".join(page.text)
    assert "pip install -e '.[view]'" in text
    assert len(page.attrs("img")) == 2 and "front claim" in page.cells and "release displacement" in page.cells
    assert not any(a.get("id", "").startswith("plot-") for _, a in page.tags)
    assert not any("Plotly" in s for s in page.scripts)


def test_a_study_without_charts_or_figures_still_has_its_section(tmp_path):
    """No claims, no quantities, no summaries of trials: no empty tables, no plotly.js, the study's section."""
    page = parse(write_html_report(tmp_path, [StudyResult("servo", {"step_um": 500.0}, [], ["Poles."], [])], {}))
    ids = {a.get("id") for _, a in page.tags}
    assert "study-servo" in ids and "claims" not in ids and "quantities" not in ids
    assert not page.cells and not any(len(s) > 100_000 for s in page.scripts)
