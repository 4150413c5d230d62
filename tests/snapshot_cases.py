"""Wrong values for every field of a saved chain snapshot (``ChainSnapshot``), each of a kind
``ChainSnapshot.freeze`` never writes: the retained-state tests corrupt a saved test with
them (issue 26, finding 5). A field added to the snapshot without its cases fails
``test_every_field_of_a_snapshot_has_wrong_values_to_try``."""

from __future__ import annotations

BAD_VALUES: dict[str, tuple[object, ...]] = {
    "state": ("Xunning", "running", "", None, 4),
    "recipe": (None, 7, "two\nlines", ["r"]),
    "test_id": (None, 12, "t1\n", {"id": "t1"}),
    "step": (-1, 1.5, "0", None, True),
    "step_id": (None, 3, "a\tb"),
    "cycle": (0, -3, 1.0, "1", None, False),
    "step_count": (-1, 2.5, None, "3"),
    "test_time_s": (-5.0, float("nan"), float("inf"), "10", None, True),
    "cycle_time_s": (-0.5, float("nan"), "1", None),
    "step_time_s": (-1.0, float("-inf"), None, [1.0]),
    "group_time_s": ([], {"a": 1.0}, {"0": -1.0}, {"0": float("nan")}, {"0": "1"}, None),
    "sleep_until_wall": (-1.0, float("nan"), "soon", True),
    "sleep_then": (-1, 1.5, "2", True),
    "q0_ah": (float("nan"), float("inf"), None, "0.1", True),
    "step_q0_ah": (float("nan"), None, "0"),
    "step_e0_wh": (float("-inf"), None, "0"),
    "test0": ([], None, {"charged_ah": "1"}, {"volts": 1.0}, {"charged_ah": float("nan")}),
    "cycle0": ("x", None, {"discharged_wh": -1.0}, {"charged_ah": None}),
    "since_record_s": (-1.0, float("nan"), "1"),
    "last_rec_v": (float("nan"), "1.2", True),
    "last_rec_i": (float("inf"), "0.1", False),
    "end_reason": (None, 1, ["done"]),
    "max_time_acked": (0, 1, "true", None),
    "alarm": (None, False, 3),
    "peak_v": (float("nan"), "1.4", True),
    "wall": (-1.0, float("nan"), None, "2026-01-01"),
    "format": (0, 2, "1", None),
}
