"""The HTML report is self-contained, escapes its text and records how it was made."""

import base64

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import pandas as pd
import pytest

from bayesdrive.data.atomic import write_atomic
from bayesdrive.reports.html import Report


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
