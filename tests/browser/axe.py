"""axe-core (npm, tests/browser/node_modules: ``make axe``) run on a page by Python
Playwright: the accessibility check of every screen (issue 33, "What to build").

The engine is evaluated through the DevTools protocol (``page.evaluate``), not added as a
``<script>``: the supervisor's Content-Security-Policy allows only its own scripts, and the
check must see the page as the operator gets it, under that policy. Rules are axe-core's
WCAG 2.x A and AA sets and its best practices; a violation of impact ``serious`` or
``critical`` fails the test, the others are reported with the figures."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

AXE_JS = Path(__file__).resolve().parent / "node_modules" / "axe-core" / "axe.min.js"
TAGS = ["wcag2a", "wcag2aa", "wcag21a", "wcag21aa", "wcag22aa", "best-practice"]
BLOCKING = frozenset({"serious", "critical"})


@dataclass(frozen=True)
class Violation:
    rule: str
    impact: str
    help: str
    targets: tuple[str, ...]
    why: tuple[str, ...] = ()
    """axe-core's message for each target (a contrast's colours and ratio, ...)."""

    def __str__(self) -> str:
        shown = ", ".join(self.targets[:4]) + (" …" if len(self.targets) > 4 else "")
        return f"{self.impact} {self.rule}: {self.help} ({len(self.targets)}: {shown})"

    def detail(self) -> str:
        """Each target with axe-core's reason, one a line."""
        return "\n".join(f"    {t}: {w}" for t, w in zip(self.targets, self.why, strict=False))


@cache
def _source() -> str:
    if not AXE_JS.exists():
        raise AssertionError(f"{AXE_JS} is missing: `make axe` installs axe-core (npm ci)")
    return AXE_JS.read_text(encoding="utf-8")


def audit(page: Any) -> list[Violation]:
    """axe-core's violations on ``page`` as it is now (the whole document)."""
    if not page.evaluate("() => typeof window.axe === 'object'"):
        page.evaluate(_source())
    found = page.evaluate(
        """async (tags) => {
            const r = await axe.run(document, {runOnly: {type: 'tag', values: tags},
                                               resultTypes: ['violations']});
            return r.violations.map(v => ({rule: v.id, impact: v.impact || 'minor',
                help: v.help, targets: v.nodes.map(n => n.target.join(' ')),
                why: v.nodes.map(n => [...n.any, ...n.all, ...n.none]
                                      .map(c => c.message).join('; '))}));
        }""",
        TAGS,
    )
    return [
        Violation(v["rule"], v["impact"], v["help"], tuple(v["targets"]), tuple(v["why"]))
        for v in found
    ]


def blocking(violations: list[Violation]) -> list[Violation]:
    """The serious and critical ones (the issue's bar: none)."""
    return [v for v in violations if v.impact in BLOCKING]
