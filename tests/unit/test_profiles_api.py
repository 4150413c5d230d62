"""The profile upload's job (hmi/profiles_api.py), pure: what the Recipes screen's preview
shows of a profile CSV, and the profiles the screens leave to the command line."""

from __future__ import annotations

from supervisor.hmi.profiles_api import MAX_CHART_POINTS, MAX_TABLE_ROWS, profile_job


def csv(rows: int) -> bytes:
    lines = ["Time (s),Current (A)"] + [f"{k},{0.1 if k % 2 else -0.1}" for k in range(rows)]
    return ("\n".join(lines) + "\n").encode()


def test_a_long_profile_s_preview_keeps_a_bounded_table_and_chart_ending_at_its_end() -> None:
    answer = profile_job(csv(20_000), "long.csv", "long.csv", None)
    assert answer["ok"] and answer["rows"] == 20_000
    assert len(answer["table"]) == MAX_TABLE_ROWS
    chart = answer["chart"]
    assert len(chart["t_s"]) <= MAX_CHART_POINTS
    assert chart["t_s"][0] == 0.0 and chart["t_s"][-1] == 19_999.0


def test_a_profile_too_long_for_a_recipe_inline_is_refused_with_the_way_round() -> None:
    answer = profile_job(csv(40_000), "huge.csv", "huge.csv", None)
    (error,) = answer["errors"]
    assert error["file"] == "huge.csv"
    assert "`supervisor import profile` makes a recipe that names the CSV" in error["message"]


def test_the_recipe_is_named_after_the_uploaded_file() -> None:
    answer = profile_job(csv(3), "x", "Essai 12 (copie).csv", None)
    assert answer["recipe"] == "Essai-12-copie"
    assert "recipe: Essai-12-copie" in answer["text"]
