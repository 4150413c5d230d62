"""What a SIGKILL loses of a running test's charge counters: at most one retained-state save
period (docs/operator.md "Retained state"). A real ``supervisor run`` on the seed 002 bench (its
devices simulated in the same process: only the counters matter here) charges the pack at
a known current; the test reads ``ch4.charged_ah`` over HTTP and kills the process by its
pid right after the answer, then reads what ``state.sqlite`` holds for the channel (what a
restart brings back). The counter read is a lower bound of the counter at the kill, so the
difference is a lower bound of what was lost: it must stay within the charge of one save
period at the known current."""

from __future__ import annotations

import random
import sys
import time
from functools import partial
from pathlib import Path

import pytest
import yaml

from supervisor.bench.killrestart import (
    _connected,
    _http,
    _in_state,
    _Process,
    _wait,
    kill_restart_map,
)
from supervisor.publish.retain import STATE_NAME, RetainStore

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.integration
SEED = 26
KILLS = 3
CURRENT_A = 10.0
RECIPE = f"""\
recipe: kill-loss
logging: {{period: 1 s}}
steps:
  - {{id: charge, charge: {CURRENT_A:g} A, duration: 10 min}}
"""


def _charging(url: str) -> bool:
    return abs(float(_http("GET", f"{url}/tags/ch4.current")["value"]) - CURRENT_A) < 0.2


@pytest.mark.timeout(300)
def test_a_sigkill_loses_at_most_one_save_period_of_charge(tmp_path: Path) -> None:
    bench_map = kill_restart_map(tmp_path, str(ROOT / "io_maps" / "sim.yaml"))
    data = yaml.safe_load(bench_map.read_text(encoding="utf-8"))
    period_s = float((data.get("retain") or {}).get("period_s", 1.0))
    recipe = tmp_path / "kill-loss.yaml"
    recipe.write_text(RECIPE, encoding="utf-8")
    state = tmp_path / "var" / STATE_NAME
    rng = random.Random(SEED)
    exe = [sys.executable, "-m", "supervisor.cli.main", "run", str(bench_map)]
    losses_s: list[float] = []
    for k in range(KILLS):
        p = _Process([*exe, "--log-level", "warning"], tmp_path, tmp_path / "logs.txt")
        try:
            url = ""
            for line in p.banner("Ctrl-C"):
                if line.startswith("HTTP API listening on "):
                    url = line.split()[-1].removesuffix("/tags")
            _wait("devices connected", partial(_connected, url))
            if k == 0:
                _http("PUT", f"{url}/channels/ch4/recipe", {"file": str(recipe)})
                _http("PUT", f"{url}/tags/ch4.command", {"value": "start"})
            else:  # restored Held: resumed
                _wait("Held", partial(_in_state, url, ("Held",)))
                _http("PUT", f"{url}/tags/ch4.command", {"value": "resume"})
            _wait("Running", partial(_in_state, url, ("Running",)))
            # The current established (the supply's ramp is not what this measures).
            _wait("the charge current", partial(_charging, url))
            time.sleep(rng.uniform(1.0, 3.0))
            read_ah = float(_http("GET", f"{url}/tags/ch4.charged_ah")["value"])
            p.kill()
        finally:
            p.stop()
        saved = RetainStore(state).read()["channel:ch4"]
        saved_ah = float(saved["tags"]["ch4.charged_ah"])
        losses_s.append((read_ah - saved_ah) * 3600.0 / CURRENT_A)
    worst_s = max(losses_s)
    assert worst_s <= period_s, (
        f"a SIGKILL lost {worst_s:.3f} s of charge at {CURRENT_A:g} A (save period"
        f" {period_s:g} s); every kill: {[round(x, 3) for x in losses_s]}"
    )
