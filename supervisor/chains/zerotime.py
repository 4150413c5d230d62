"""Loops that let no time pass: found in the compiled steps before anything runs (ADR 0011).

A step *ends at once* when, whatever is measured, it can end in the scan it starts: it is
a ``goto`` or an ``end_cycle`` (instant, ADR 0004), its own time is 0 s (``rest: 0 s``,
``duration: 0 s``, ``sleep: 0 s``, a profile whose rows all start at 0 s), a group it is
in lasts 0 s, or one of its (or its groups') ``until`` conditions is true at step time 0
with nothing measured (``true``, ``step_time >= 0 s``, ``step_time < 1 min``): the
condition is evaluated as the engine does, three-valued, with ``step_time`` 0, the
parameters at their values and every other name unknown.

From a step that ends at once, every way out that can act in that scan is a *zero-time
edge*: its sure exit and, before it in the engine's order (ADR 0004: the step's
conditions, its groups' conditions, the end of a sleep or profile, the duration, the
groups' durations), any condition that depends on a measurement (it may be true at once).
The end of the steps, an ``end_cycle`` and a ``next_cycle`` lead to the first step when
``cycles`` is above 1. A cycle made only of zero-time edges is a loop that can run through
every one of its steps without time passing: refused.

A loop of steps that end by measured conditions only (charge until ``voltage >= v_max``,
discharge until ``voltage <= v_min``, back to the charge) is how cycling is written and is
not refused: every such step lasts at least one scan, the engine bounds what can happen
in one scan (``MAX_TRANSITIONS_PER_SCAN``) and a dry run ends at its ``--max-hours`` cap.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from supervisor.chains.program import Action, ActionKind, CompiledGroup, CompiledStep

__all__ = ["Exit", "ZeroTimeLoop", "describe", "exits_at_once", "zero_time_loops"]

EPS_S = 1e-9
"""A time up to float noise counts as 0 s (the engine's ``EPS_S``: a duration this short
is reached in the scan the step starts)."""

Path = tuple[str | int, ...]


@dataclass(frozen=True, slots=True)
class Exit:
    """One way out of a step that can act in the scan the step starts."""

    target: int | None
    """The step it leads to (``len(steps)``: the start of the next cycle; None: no step,
    e.g. ``end``, ``hold``, a sleep that takes time)."""
    label: str  # what ends the step: "rest 0 s", "until #1 'true' is true at once"
    path: Path  # where it is written in the recipe
    at_key: bool  # point at the key (an ``until`` condition) rather than its value
    sure: bool  # acts whatever is measured (the step ends at once)


@dataclass(frozen=True, slots=True)
class ZeroTimeLoop:
    """A cycle of zero-time edges: ``nodes[0] → nodes[1] → … → nodes[0]``."""

    nodes: tuple[int, ...]  # step indices; ``len(steps)`` stands for the next cycle
    edges: tuple[Exit, ...]  # edges[k] leaves nodes[k]
    reasons: tuple[Exit, ...]  # reasons[k]: why nodes[k] ends at once (its sure exit)


def exits_at_once(
    step: CompiledStep,
    steps: Sequence[CompiledStep],
    groups: Sequence[CompiledGroup],
    parameters: Mapping[str, float],
    duration_key: str = "duration",
) -> list[Exit]:
    """The exits of ``step`` that can act in the scan it starts, in the engine's order,
    up to and including the first sure one (later ones can never act first). The step
    ends at once when the last one is sure. ``duration_key``: where its duration is
    written (``rest`` for ``rest: 0 s``)."""
    i, n_steps = step.index, len(steps)
    here: Path = ("steps", i)
    if step.kind == "goto":
        target = step.goto
        to = steps[target].id if target is not None and 0 <= target < n_steps else "?"
        return [Exit(target, f"goto {to}", (*here, "goto"), False, True)]
    if step.kind == "end_cycle":
        return [Exit(n_steps, "end_cycle", (*here, "end_cycle"), False, True)]
    if step.kind == "end":
        return [Exit(None, "end", (*here, "end"), False, True)]
    if step.kind == "sleep_until":
        return []  # waits for a time of day: never at once twice in a row
    values: dict[str, float | bool | None] = {"step_time": 0.0, **parameters}
    out: list[Exit] = []
    lists = [("until #", (*here, "until"), step.transitions)]
    lists += [
        (f"group {groups[g].id} until #", ("groups", g, "until"), groups[g].transitions)
        for g in step.groups
        if g < len(groups)
    ]
    for what, at, transitions in lists:
        for tr in transitions:
            value = tr.condition.evaluate(values)
            if value is False or (value is None and not _measured(tr.condition.names, values)):
                continue  # false at step time 0 (or unknown with nothing measured)
            sure = value is True
            label = f"{what}{tr.index} {tr.text!r} " + ("is true" if sure else "may be true")
            path = (*at, tr.index - 1, tr.text)
            out.append(Exit(_target(tr.action, i, n_steps), label + " at once", path, True, sure))
            if sure:
                return out
    nxt = i + 1
    if step.kind == "sleep" and step.sleep_s is not None and step.sleep_s <= EPS_S:
        return [*out, Exit(nxt, "sleep 0 s", (*here, "sleep"), False, True)]
    if step.kind == "profile" and step.profile and step.profile[-1].t_s <= EPS_S:
        return [*out, Exit(nxt, "profile of 0 s", (*here, "profile"), False, True)]
    if step.duration_s is not None and step.duration_s <= EPS_S:
        label = f"{duration_key} 0 s"
        return [*out, Exit(nxt, label, (*here, duration_key), False, True)]
    for g in step.groups:
        if g < len(groups) and (d := groups[g].duration_s) is not None and d <= EPS_S:
            after = max(groups[g].steps) + 1
            label = f"group {groups[g].id} lasts 0 s"
            return [*out, Exit(after, label, ("groups", g, "duration"), False, True)]
    return out


def zero_time_loops(
    steps: Sequence[CompiledStep],
    groups: Sequence[CompiledGroup],
    cycles: int,
    parameters: Mapping[str, float],
    duration_keys: Sequence[str] | None = None,
) -> list[ZeroTimeLoop]:
    """One loop per strongly connected set of zero-time edges, each the shortest cycle
    through its lowest-numbered step, in step order."""
    n = len(steps)
    edges: dict[int, list[Exit]] = {}
    reasons: dict[int, Exit] = {}
    for s in steps:
        key = duration_keys[s.index] if duration_keys is not None else "duration"
        exits = exits_at_once(s, steps, groups, parameters, key)
        if exits and exits[-1].sure:
            reasons[s.index] = exits[-1]
            edges[s.index] = [e for e in exits if e.target is not None and 0 <= e.target <= n]
    if cycles > 1:
        restart = Exit(0, f"cycles: {cycles}", ("cycles",), False, True)
        edges[n] = [restart]
        reasons[n] = restart
    loops = []
    for component in _components(edges):
        start = min(component)
        path = _shortest_cycle(start, component, edges)
        if path is not None:
            nodes = tuple(e_from for e_from, _ in path)
            loops.append(
                ZeroTimeLoop(nodes, tuple(e for _, e in path), tuple(reasons[k] for k in nodes))
            )
    return sorted(loops, key=lambda loop: loop.nodes[0])


def describe(loop: ZeroTimeLoop, steps: Sequence[CompiledStep]) -> tuple[str, str]:
    """The loop's path (``b → c → b``) and what ends each of its steps at once."""
    n = len(steps)

    def name(k: int) -> str:
        return "(next cycle)" if k == n else steps[k].id

    path = " → ".join(name(k) for k in (*loop.nodes, loop.nodes[0]))
    details = []
    for k, edge, reason in zip(loop.nodes, loop.edges, loop.reasons, strict=True):
        if k == n:
            details.append(f"{edge.label} starts it again")
            continue
        text = f"{steps[k].id}: {edge.label}"
        if not edge.sure:
            text += f", else {reason.label}"
        details.append(text)
    return path, "; ".join(details)


def _measured(names: frozenset[str], known: Mapping[str, object]) -> bool:
    """The condition reads something only a measurement (or the run) gives."""
    return any(name not in known for name in names)


def _target(action: Action, index: int, n_steps: int) -> int | None:
    k = action.kind
    if k is ActionKind.NEXT:
        return index + 1
    if k is ActionKind.GOTO:
        return action.target
    if k is ActionKind.NEXT_CYCLE:
        return n_steps
    if k is ActionKind.SLEEP and (action.seconds or 0.0) <= EPS_S:
        return index + 1  # "+00:00": wakes in the next scan, on to the next step
    return None  # end, hold, a sleep that takes time


def _components(edges: Mapping[int, list[Exit]]) -> list[set[int]]:
    """Strongly connected components with at least one cycle (Tarjan, iterative: a
    recipe may have thousands of steps)."""
    index: dict[int, int] = {}
    low: dict[int, int] = {}
    on_stack: set[int] = set()
    stack: list[int] = []
    found: list[set[int]] = []
    counter = 0

    def successors(v: int) -> list[int]:
        return [e.target for e in edges.get(v, ()) if e.target is not None and e.target in edges]

    for root in sorted(edges):
        if root in index:
            continue
        work: list[tuple[int, int]] = [(root, 0)]
        while work:
            v, pos = work.pop()
            if pos == 0:
                index[v] = low[v] = counter
                counter += 1
                stack.append(v)
                on_stack.add(v)
            succ = successors(v)
            if pos < len(succ):
                work.append((v, pos + 1))
                w = succ[pos]
                if w not in index:
                    work.append((w, 0))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            if low[v] == index[v]:
                component = set()
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    component.add(w)
                    if w == v:
                        break
                if len(component) > 1 or v in successors(v):
                    found.append(component)
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[v])
    return found


def _shortest_cycle(
    start: int, component: set[int], edges: Mapping[int, list[Exit]]
) -> list[tuple[int, Exit]] | None:
    """Breadth first from ``start`` back to it inside ``component``: (node, edge) pairs."""
    came: dict[int, tuple[int, Exit]] = {}
    frontier = [start]
    while frontier:
        nxt: list[int] = []
        for v in frontier:
            for e in edges.get(v, ()):
                w = e.target
                if w is None or w not in component:
                    continue
                if w == start:
                    path = [(v, e)]
                    while v != start:
                        u, edge = came[v]
                        path.append((u, edge))
                        v = u
                    return path[::-1]
                if w not in came:
                    came[w] = (v, e)
                    nxt.append(w)
        frontier = nxt
    return None
