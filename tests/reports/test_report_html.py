"""The HTML report is self-contained, escapes its text and records how it was made."""

import base64
from html.parser import HTMLParser
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import pandas as pd
import pytest

from bayesdrive.data.atomic import write_atomic
from bayesdrive.reports.html import Report
from bayesdrive.reports.paper_report import holdout_section


def test_report_embeds_figures_tables_and_provenance(tmp_path):
    png = tmp_path / "curve.png"
    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    fig.savefig(png)
    plt.close(fig)

    report = Report("Title <&>", intro="intro text")
    section = report.section("Results")
    section.text("a < b").note("differs from the paper")
    section.table(pd.DataFrame({"model": ["idm"], "rmse": [1.23456]}), caption="RMSE")
    section.figure(png, "the curve")
    out = report.write(tmp_path / "report.html", command=["bayesdrive", "report", "--out", "x"])

    page = out.read_text()
    assert "Title &lt;&amp;&gt;" in page and "a &lt; b" in page
    assert base64.b64encode(png.read_bytes()).decode("ascii") in page
    assert "1.23" in page and "<table" in page
    assert "bayesdrive report --out x" in page
    assert "jax" in page and "numpyro" in page


def test_crash_mid_write_leaves_no_half_file(tmp_path):
    target = tmp_path / "report.html"
    target.write_text("previous complete report")

    def half_then_crash(tmp):
        tmp.write_text("<html><body>half")
        raise RuntimeError("killed mid-write")

    with pytest.raises(RuntimeError):
        write_atomic(target, half_then_crash)
    assert target.read_text() == "previous complete report"
    assert [p.name for p in tmp_path.iterdir()] == ["report.html"]


# Vehicle ids are text from the user's file (the column-map reader keeps them as written).
HOSTILE_IDS = ('<script>alert("id")</script>', '"><img src=x onerror=alert(1)>')


class _Page(HTMLParser):
    """The tags a browser would build from a page, and its text and attribute values."""

    def __init__(self, page: str):
        super().__init__(convert_charrefs=True)
        self.tags, self.texts = [], []
        self.feed(page)

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))
        self.texts.extend(value for _, value in attrs if value)

    def handle_data(self, data):
        self.texts.append(data)


def test_hostile_vehicle_ids_are_escaped_wherever_a_report_shows_them(tmp_path):
    script, attribute = HOSTILE_IDS
    png = tmp_path / "posterior.png"
    png.write_bytes(b"image bytes")  # figure() embeds the bytes as they are
    report = Report(f"Fit of vehicle {script}", intro=f"vehicles {script}, {attribute}")
    section = report.section(f"vehicle {script}")
    section.text(f"fitted {script}").note(f"skipped {attribute}").code(f"vehicle {script}")
    per_vehicle = pd.DataFrame({"vehicle": list(HOSTILE_IDS), "v_des": [30.1, 29.5]})
    section.table(per_vehicle, caption=f"posterior means of {script}")
    section.table(per_vehicle.set_index("vehicle").T.reset_index(), caption="one column each")
    section.figure(png, f"posterior of {attribute}")
    holdout = {"protocol": "protocol", "data_sets": {"mine": {"error": f"vehicle {script}: no"}}}
    holdout_section(report.section("Held out"), holdout)
    command = ["bayesdrive", "fit", attribute]
    page = _Page(report.write(tmp_path / "report.html", command=command).read_text())

    assert [tag for tag, _ in page.tags if tag == "script"] == []
    assert [attrs for _, attrs in page.tags if "onerror" in attrs] == []
    # Each place shows the id as text: title and heading, intro, contents and section heading,
    # text, code, caption, table cell, column header, held-out note; the other id in the intro,
    # note, table cell, column header, figure alt text and caption, and the command.
    assert sum(text.count(script) for text in page.texts) == 11
    assert sum(text.count(attribute) for text in page.texts) == 7


def test_a_moved_results_folder_finds_its_figures_by_name(tmp_path):
    """A reproduction records a step's figures by name (earlier runs: whole paths inside their
    staging folder, ``.results.partial``); after the folder is renamed or moved, the report
    finds them in the step's folder where they now are. Negative control: the whole path an
    earlier run recorded no longer exists."""
    from bayesdrive.reports.paper_report import criticism_folder, figure_paths

    moved = criticism_folder(tmp_path / "moved", "openacc_vicolungo:human")
    moved.mkdir(parents=True)
    (moved / "causes.png").write_bytes(b"png")
    recorded_then = str(tmp_path / ".results.partial" / "criticism" / "x" / "causes.png")
    assert not Path(recorded_then).exists()
    for recorded in (["causes.png"], [recorded_then]):
        assert figure_paths(recorded, moved) == [moved / "causes.png"]
        assert figure_paths(recorded, moved)[0].read_bytes() == b"png"


def test_the_pit_legend_names_every_model_even_when_the_first_set_has_one(tmp_path, monkeypatch):
    """The first held-out set forecast by the IDM alone, the second by the IDM and an adopted
    extension: the legend names both, and each model keeps its colour in every panel."""
    from bayesdrive.reports import paper_report

    def forecast(counts):
        return {"starts": {"filtered": {"horizons": {"5": {"windows": 4, "pit_counts": counts}}}}}

    data_sets = {
        "a": {"models": {"idm": forecast([1, 1, 1, 1])}},
        "b": {"models": {"idm": forecast([2, 0, 0, 2]), "idm+x": forecast([0, 2, 2, 0])}},
    }
    saved = []
    monkeypatch.setattr(paper_report, "_save", lambda fig, path: saved.append(fig) or path)
    paper_report.plot_pit_histograms(data_sets, tmp_path / "pit.png")
    (legend,) = saved[0].legends
    assert [t.get_text() for t in legend.get_texts()] == ["idm", "idm+x"]
    first, second = saved[0].axes
    colours = [[p.get_edgecolor() for p in ax.patches] for ax in (first, second)]
    assert colours[0][0] == colours[1][0] != colours[1][1]
