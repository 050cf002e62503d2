"""The report's Turing table: both classifiers' accuracies side by side for every model."""

from bayesdrive.reports.paper_report import turing_table


def row(accuracy: float, p_value: float) -> dict:
    return {
        "accuracy": accuracy,
        "ci_low": accuracy - 0.05,
        "ci_high": accuracy + 0.05,
        "p_value": p_value,
    }


def test_both_classifiers_side_by_side_and_older_results_without_the_boosted_one():
    rows = {
        "idm-smc": {**row(0.7, 0.01), "levels_only": row(0.55, 0.2), "boosted": row(0.82, 0.02)},
        # Saved before the boosted classifier existed.
        "cv": {**row(0.99, 0.005), "levels_only": row(0.96, 0.005)},
    }
    table = turing_table(rows).set_index("model")
    assert table.loc["idm-smc", "accuracy, logistic"] == "0.700"
    assert table.loc["idm-smc", "accuracy, boosted"] == "0.820"
    assert table.loc["idm-smc", "95% CI, boosted (approx.)"] == "0.77-0.87"
    assert table.loc["idm-smc", "p, boosted"] == "0.020"
    assert table.loc["cv", "accuracy, logistic on levels only"] == "0.960"
    assert (
        table.loc["cv", ["accuracy, boosted", "95% CI, boosted (approx.)", "p, boosted"]].tolist()
        == ["-"] * 3
    )
