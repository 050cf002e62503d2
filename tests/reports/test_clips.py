"""Turing-test material: two clips per pair in the same styling, the real one's letter recorded."""

import json

import numpy as np
from PIL import Image

from bayesdrive.reports.clips import write_answer_sheet, write_clip_pair


def test_clip_pairs_and_answer_sheet(tmp_path):
    t = np.arange(21) * 0.1
    real = np.stack([60 + 15 * t, 40 + 14 * t])
    simulated = np.stack([60 + 15 * t, 40 + 13 * t])
    rng = np.random.default_rng(7)
    entries = [
        write_clip_pair(real, simulated, np.full(2, 4.5), 0.1, tmp_path, f"p{i}", rng)
        for i in range(6)
    ]
    sheet = json.loads(write_answer_sheet(entries, tmp_path / "answers.json").read_text())
    # the order comes from the seeded generator: the same seed gives the same sheet
    replay = np.random.default_rng(7)
    assert [e["real"] for e in sheet] == ["A" if replay.integers(2) else "B" for _ in range(6)]
    for entry in sheet:
        for letter in "AB":
            with Image.open(tmp_path / f"{entry['pair']}_{letter}.gif") as clip:
                assert clip.n_frames == 11  # every second of 21 steps
    assert not list(tmp_path.glob(".*"))  # no temporary files left behind
