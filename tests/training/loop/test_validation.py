"""The validation table: per-level errors, and how much darker than its data each level answers."""

import numpy as np

from neumip.training.loop.validation import format_table, validation_table


def test_each_level_reports_its_data_over_its_answers_mean():
    sigma = np.array([0.0, 0.0, 8 / 64, 8 / 64])  # levels 0 and 3 of a 64^2 pyramid
    target = np.full((4, 3), 0.4, np.float32)
    pred = target * np.array([1.0, 1.0, 0.5, 0.5], np.float32)[:, None]
    table = validation_table(pred, target, sigma, 64)
    rows = {r["level"]: r for r in table["levels"]}
    assert rows[0]["answer_mean"] == rows[0]["target_mean"]
    assert np.isclose(rows[3]["target_mean"] / rows[3]["answer_mean"], 2.0)
    lines = format_table(table).splitlines()
    assert "data / answer" in lines[0]
    assert lines[1].split()[-1] == "1.000" and lines[2].split()[-1] == "2.000"


def test_a_table_from_before_the_answers_mean_still_formats():
    table = validation_table(np.ones((2, 3), np.float32), np.ones((2, 3), np.float32), np.zeros(2), 16)
    for row in table["levels"] + [table["overall"]]:
        del row["answer_mean"]
    assert len(format_table(table).splitlines()) == 3
