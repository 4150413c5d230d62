"""``supervisor run --recipe CH=FILE [--start]`` takes the command path: a refusal is one
clear message and exit code 2, before anything is started or served."""

from __future__ import annotations

from pathlib import Path

import pytest
from commandrig import CV_ON_CHADECHE, DISCHARGE, chadeche_map, recipe

from supervisor.cli.main import main


def run(tmp: Path, *args: str) -> int:
    return main(["run", chadeche_map(tmp), "--http-port", "0", *args])


def test_a_recipe_the_channel_cannot_do_is_refused_with_its_location_and_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = recipe(tmp_path, CV_ON_CHADECHE, "cv.yaml")
    assert run(tmp_path, "--recipe", f"ch0={bad}", "--start") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0].startswith(
        f"supervisor: --recipe ch0={bad}: start refused: ch0: recipe refused: {bad}:"
    )
    assert "Traceback" not in "\n".join(err)


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("ch9={ok}", "load refused: unknown channel 'ch9' (channels: ch0, ch1, ch2, ch3)"),
        ("ch0={missing}", "load refused: {missing}: no such recipe"),
    ],
)
def test_an_unknown_channel_or_file_is_refused_with_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], spec: str, message: str
) -> None:
    names = {"ok": recipe(tmp_path, DISCHARGE), "missing": str(tmp_path / "missing.yaml")}
    spec, message = spec.format(**names), message.format(**names)
    assert run(tmp_path, "--recipe", spec) == 2
    assert capsys.readouterr().err.strip() == f"supervisor: --recipe {spec}: {message}"


def test_a_device_given_as_the_recipe_is_refused_by_its_size_not_read_forever(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert run(tmp_path, "--recipe", "ch0=/dev/zero") == 2
    assert capsys.readouterr().err.strip() == (
        "supervisor: --recipe ch0=/dev/zero: load refused: ch0: recipe refused: /dev/zero:"
        " file is too large: more than 1 MiB; a recipe may have at most 1 MiB"
        " (README: Input limits)"
    )
