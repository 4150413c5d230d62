"""The software e-stop's button on the Overview (issue 32, finding 7), in Debian's Chromium
against a real ``supervisor run`` of the simulated bench (io_maps/sim.yaml on free ports):
the one red button of the screen (ISA-101), behind a confirmation; Cancel does nothing; the
operator's press makes the EA channel's pack safe on the simulated plant (no current, supply
output off, contactor open), not only its alarm; the reset is refused with the reason until
the alarm is acknowledged; a viewer's press is refused and trips nothing.
"""

from __future__ import annotations

from typing import Any

from browserrig import Supervisor, login, result_text, screenshot, wait_for

RED = "rgb(200, 16, 46)"  # --alarm in hmi/css/hmi.css


def pack_current_a(bench: Supervisor) -> float:
    """The LEM sensor's reading of the pack's current (ADAM 5017, the simulated plant's)."""
    return float(bench.tag("pack.current"))


def outputs_safe(bench: Supervisor) -> bool:
    """The plant as its own sensors read it back: the supply's output off (``OUTP?``), the
    contactor's auxiliary contact open, no current through the LEM sensor (its noise aside)."""
    return (
        bench.tag("ea.output_on") is False
        and bench.tag("contactor.closed") is False
        and abs(pack_current_a(bench)) < 0.05
    )


def estop_state(bench: Supervisor) -> str:
    status, body = bench.call("GET", "/api/alarms")
    assert status == 200, body
    return next((a["state"] for a in body["active"] if a["id"] == "estop"), "normal")


def result(page: Any) -> str:
    return result_text(page, "#estop-result")


def test_the_overview_estop_is_the_one_red_button_and_asks_first(
    page: Any, bench: Supervisor
) -> None:
    login(page, bench, "operator")
    page.wait_for_selector("#estop-press")
    colours = page.eval_on_selector_all(
        "button",
        "bs => bs.filter(b => b.checkVisibility())"
        ".map(b => [b.id, getComputedStyle(b).backgroundColor])",
    )
    assert [i for i, c in colours if c == RED] == ["estop-press"], colours
    page.click("#estop-press")
    assert page.locator("#estop-confirm").is_visible()
    screenshot(page, "overview-estop-confirm")
    page.click("#estop-confirm-no")
    assert not page.locator("#estop-confirm").is_visible()
    assert page.locator("#estop-result").is_hidden()
    assert estop_state(bench) == "normal"


def test_a_viewer_s_press_is_refused_with_the_reason(page: Any, bench: Supervisor) -> None:
    login(page, bench, "viewer")
    page.click("#estop-press")
    page.click("#estop-confirm-yes")
    text = result(page)
    assert text.startswith("Refused (403)") and "viewer" in text, text
    assert estop_state(bench) == "normal"


def test_the_operator_s_press_makes_the_pack_safe_and_the_reset_waits_for_the_ack(
    page: Any, bench: Supervisor
) -> None:
    wait_for("ch4's devices", lambda: bench.tag("ea.connected") and bench.tag("estop.ok"))
    for tag, value in (("ch4.manual_current", 2.0), ("ch4.enable", True)):
        status, body = bench.call("PUT", f"/api/tags/{tag}", {"value": value})
        assert status == 200, body
    wait_for(
        "2 A into the pack, the supply on, the contactor closed",
        lambda: (
            abs(pack_current_a(bench) - 2.0) < 0.1
            and bench.tag("ea.output_on") is True
            and bench.tag("contactor.closed") is True
        ),
    )
    login(page, bench, "operator")
    page.click("#estop-press")
    page.click("#estop-confirm-yes")
    text = result(page)
    assert text.startswith("software e-stop pressed by hmi:operator"), text
    # What the screen says is true of the hardware, as the plant's own sensors read it.
    wait_for("the pack disconnected and the supply off", lambda: outputs_safe(bench))
    assert bench.tag("ch4.state") == "faulted" and bench.tag("ch4.current_cmd") == 0.0
    # And the screen shows it: the mimic's supply off and contactor open, ch4 tripped.
    page.wait_for_function(
        "() => document.querySelector('#tile-ch4').classList.contains('abn')"
        " && document.querySelector('#mimic-supply').textContent.includes('off')"
        " && document.querySelector('#mimic-contactor').textContent.includes('open')"
        " && document.querySelector('#estop-trip').textContent"
        ".includes('Software e-stop pressed by hmi:operator')"
    )
    screenshot(page, "overview-software-estop")
    page.click("#estop-reset")
    text = result(page)
    assert text.startswith("Refused (409)") and "acknowledge the e-stop first" in text, text
    status, body = bench.call("POST", "/api/alarms/estop/acknowledge", {})
    assert status == 200, body
    page.click("#estop-reset")
    page.wait_for_function(
        "() => document.querySelector('#estop-result').textContent.startsWith('e-stop reset')"
    )
    assert estop_state(bench) == "normal"
    # Released, nothing is energised again on its own.
    assert bench.tag("ch4.enable") is False
    assert outputs_safe(bench)
