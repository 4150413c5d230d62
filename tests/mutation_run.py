"""Feed the project's mutation corpus (``tests/mutation.py``) to the real commands.

    python -m tests.mutation_run N [--seed S] [--jobs J] [--timeout-s T] [--out DIR]
    python -m tests.mutation_run --show INDEX [--seed S] [--only CLASS] [--small]

Each variant is written to ``DIR/variants/`` and run in its own process through the installed
``supervisor`` command (``supervisor check FILE``, ``supervisor import chadeche FILE [--prm
P]``; a load profile through ``supervisor check`` of a one-step recipe naming it) with a time
limit and an address-space cap, ``--jobs`` at a time (a process pool, one worker per CPU by
default), then classified by :func:`tests.mutation.classify`:

* ``located``: exit 2, every stderr line ``file:line:col: message`` naming the mutated file;
* ``file_only``: exit 2 with ``file: message`` lines, for a variant over its byte limit only
  (README "Input limits": such a file is refused before it is read, there is no line);
* ``accepted``: exit 0 (``miss`` when the variant is certainly invalid);
* ``unlocated``: exit 2 with a line naming no ``file:line:col`` of the mutated file;
* ``traceback``: "Traceback" in the output, or an exit code other than 0 and 2;
* ``timeout``: still running at ``--timeout-s``;
* ``import_invalid``: an accepted import whose recipe ``supervisor check`` refuses.

The counts are printed per class and in total, and written with every failure (variant, how
it was made, command, output) to ``DIR/report.md``; every variant's outcome is one line of
``DIR/results.jsonl``; the files of the failing variants stay in ``DIR/variants/``.

Exit status 1 when a variant is a miss, unlocated, a traceback, a timeout or an invalid
import, except misses and refusals of variants labelled ``pending`` (a fix on another branch
of issue 9: listed apart, never a traceback); 0 otherwise. The wall time is printed as a
figure; nothing here asserts a speed.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

from tests.mutation import (
    DEFAULT_SEED,
    FAILURES,
    MUTATIONS,
    ROOT,
    Variant,
    Verdict,
    classify,
    make_variant,
)

DEFAULT_OUT = ROOT / "var" / "mutation"
# The categories of a run, in the order they are shown: an outcome, or "miss" for an accepted
# variant that is certainly invalid.
CATEGORIES = (
    "located",
    "file_only",
    "accepted",
    "miss",
    "unlocated",
    "traceback",
    "timeout",
    "import_invalid",
)
FAILED = frozenset({"miss", *FAILURES})
# A pending variant's fix is on another branch: these are excused until it lands, a
# traceback or a timeout never is.
EXCUSED_WHEN_PENDING = frozenset({"miss", "unlocated", "import_invalid"})


@dataclass(frozen=True)
class Record:
    """What one variant did (all a report needs; the variant's bytes stay on disk)."""

    index: int
    mutation: str
    source: str
    how: str
    expect: str
    pending: str
    whole_file: bool
    size_bytes: int
    argv: list[str]
    file: str
    code: int | None
    outcome: str
    why: str
    stderr: str
    cpu_s: float  # CPU time of the command(s), a figure for the report (never asserted)
    peak_mb: float = 0.0
    """The largest resident memory of the commands this worker ran so far, this one included
    (``RUSAGE_CHILDREN``): the largest over all records is the peak of any single command."""

    @property
    def category(self) -> str:
        return "miss" if self.outcome == "accepted" and self.expect == "refuse" else self.outcome

    @property
    def failed(self) -> bool:
        return self.category in FAILED and not self.excused

    @property
    def excused(self) -> bool:
        return bool(self.pending) and self.category in EXCUSED_WHEN_PENDING


def _limits(memory_mb: int) -> None:
    # A mutated file must not take the machine with it: the cap turns unbounded memory into a
    # MemoryError (a traceback), which is what it would be on a bench PC too.
    cap = memory_mb * 1024 * 1024
    resource.setrlimit(resource.RLIMIT_AS, (cap, cap))


def _command() -> list[str]:
    """The installed ``supervisor`` script next to this interpreter (what a user runs)."""
    script = Path(sys.executable).parent / "supervisor"
    return [str(script)] if script.exists() else [sys.executable, "-m", "supervisor.cli.main"]


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _supervisor(argv: list[str], timeout_s: float, memory_mb: int) -> tuple[int | None, str, str]:
    try:
        # preexec_fn is safe here: each pool worker is a single-threaded process.
        proc = subprocess.run(
            [*_command(), *argv],
            cwd=ROOT,
            capture_output=True,
            timeout=timeout_s,
            preexec_fn=lambda: _limits(memory_mb),
            check=False,
        )
    except subprocess.TimeoutExpired as exc:
        out = exc.stdout.decode("utf-8", "replace") if exc.stdout else ""
        err = exc.stderr.decode("utf-8", "replace") if exc.stderr else ""
        return None, out, err
    return (
        proc.returncode,
        proc.stdout.decode("utf-8", "replace"),
        proc.stderr.decode("utf-8", "replace"),
    )


def run_variant(v: Variant, workdir: Path, timeout_s: float, memory_mb: int) -> Record:
    """Write ``v``, run it through the command, classify; keep its files only if it failed."""
    feed = v.write(workdir)
    cpu_before = _children_cpu_s()  # this worker runs one command at a time
    code, out, err = _supervisor(feed.argv, timeout_s, memory_mb)
    verdict = classify(code, err, feed.files, via=feed.via, whole_file=v.whole_file)
    written = [workdir / v.file_name]
    if v.target == "profile":
        written.append((workdir / v.file_name).with_suffix(".yaml"))
    if verdict.outcome == "accepted" and v.target in ("chadeche", "prm"):
        # An import that is accepted must be a recipe `check` accepts too.
        imported = workdir / f"{Path(v.file_name).stem}.imported.yaml"
        imported.write_text(out, encoding="utf-8")
        written.append(imported)
        code2, _, err2 = _supervisor(["check", str(imported)], timeout_s, memory_mb)
        if code2 != 0:
            verdict = Verdict("import_invalid", f"check of the imported recipe: exit {code2}")
            err = err + "\n--- supervisor check of the imported recipe:\n" + err2
    record = Record(
        index=v.index,
        mutation=v.mutation,
        source=v.source,
        how=v.how,
        expect=v.expect,
        pending=v.pending,
        whole_file=v.whole_file,
        size_bytes=len(v.content),
        argv=feed.argv,
        file=feed.files[0],
        code=code,
        outcome=verdict.outcome,
        why=verdict.why,
        stderr=_excerpt(err),
        cpu_s=_children_cpu_s() - cpu_before,
        peak_mb=resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024,
    )
    if record.category not in FAILED:
        for path in written:
            path.unlink(missing_ok=True)
    return record


def _run_index(
    index: int, seed: int, only: str | None, workdir: Path, timeout_s: float, memory_mb: int
) -> Record:
    # In the worker: the variant is made from its index there (no megabytes to pickle).
    return run_variant(make_variant(index, seed, mutation=only), workdir, timeout_s, memory_mb)


def _excerpt(text: str, lines: int = 12, width: int = 300) -> str:
    """The first lines of an output, or the last ones of a traceback (where it was raised)."""
    kept = [ln[:width] + ("…" if len(ln) > width else "") for ln in text.splitlines()]
    if len(kept) > lines:
        if any(ln.startswith("Traceback") for ln in kept):
            kept = [kept[0], f"… ({len(kept) - lines + 1} lines)", *kept[-(lines - 2) :]]
        else:
            kept = [*kept[: lines - 1], f"… ({len(kept) - lines + 1} more lines)"]
    return "\n".join(kept)


_SHORT = {
    "located": "located",
    "file_only": "file only",
    "accepted": "accepted",
    "miss": "miss",
    "unlocated": "unlocated",
    "traceback": "traceback",
    "timeout": "timeout",
    "import_invalid": "bad import",
}


def summary_table(records: list[Record]) -> list[str]:
    """Per class and in total: variants, then one column per category, then pending."""
    by_class: dict[str, collections.Counter[str]] = collections.defaultdict(collections.Counter)
    for r in records:
        by_class[r.mutation][r.category] += 1
        by_class[r.mutation]["variants"] += 1
        by_class[r.mutation]["pending"] += r.excused
    total: collections.Counter[str] = collections.Counter()
    for c in by_class.values():
        total.update(c)
    cols = ["variants", *CATEGORIES, "pending"]
    head = "| class | " + " | ".join(_SHORT.get(c, c) for c in cols) + " |"
    lines = [head, "|---" * (len(cols) + 1) + "|"]
    for name in sorted(by_class):
        c = by_class[name]
        lines.append(f"| {name} | " + " | ".join(str(c[k]) for k in cols) + " |")
    lines.append("| **total** | " + " | ".join(f"**{total[k]}**" for k in cols) + " |")
    return lines


def _section(title: str, chosen: list[Record]) -> list[str]:
    lines = ["", f"## {title} ({len(chosen)})", ""]
    for r in sorted(chosen, key=lambda r: (r.category, r.mutation, r.index)):
        why = r.why or f"exit {r.code}"
        lines += [
            f"### {r.category}: #{r.index} {r.mutation} ({why})",
            "",
            f"- made from `{r.source}`: {r.how}",
            f"- expected: {r.expect}{'; whole file' if r.whole_file else ''}"
            f"{'; pending: ' + r.pending if r.pending else ''}; file: `{r.file}`",
            f"- command: `supervisor {' '.join(r.argv)}` → exit {r.code}",
            "",
            "```",
            r.stderr or "(no stderr)",
            "```",
        ]
    return lines


def write_report(
    records: list[Record],
    out: Path,
    seed: int,
    argv: list[str],
    wall_s: float,
    jobs: int,
    cpu_s: float,
) -> Path:
    failed = [r for r in records if r.failed]
    pending = [r for r in records if r.excused]
    lines = [
        "# Mutation corpus run",
        "",
        f"`python -m tests.mutation_run {' '.join(argv)}`: seed {seed}, {len(records)} variants,"
        f" {jobs} at a time, wall time {wall_s:.0f} s (CPU time of the commands {cpu_s:.0f} s).",
        "",
        f"Failures: {len(failed)}. Pending on other branches (excused until they land):"
        f" {len(pending)}.",
        "",
        *summary_table(records),
        "",
        "Columns: `located` exit 2 naming file:line:col; `file only` exit 2 naming the file of a"
        " variant over its byte limit; `accepted` exit 0 of a variant that may be valid; `miss`"
        " exit 0 of a certainly invalid one; `unlocated` exit 2 without file:line:col;"
        " `traceback` a traceback or an exit code other than 0 and 2; `timeout`; `bad import`"
        " an accepted import whose recipe `check` refuses; `pending` failures of variants"
        " waiting for another branch (counted in their column too).",
    ]
    reasons = collections.Counter(r.pending for r in pending)
    if reasons:
        lines += ["", "Pending, by branch:", ""]
        lines += [f"- {n} × {reason}" for reason, n in sorted(reasons.items())]
    lines += _section("Failures", failed)
    lines += _section("Pending on other branches", pending)
    lines += _section(
        "Refusals naming the file alone (over the byte limit)",
        [r for r in records if r.category == "file_only"],
    )
    report = out / "report.md"
    report.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return report


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m tests.mutation_run",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("count", nargs="?", type=int, default=600, help="number of variants")
    p.add_argument("--seed", type=int, default=DEFAULT_SEED)
    p.add_argument("--start", type=int, default=0, help="index of the first variant")
    p.add_argument("--only", choices=sorted(MUTATIONS), default=None, help="one class only")
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 2)
    p.add_argument("--timeout-s", type=float, default=60.0, help="per command")
    p.add_argument("--memory-mb", type=int, default=2048, help="address-space cap per command")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    p.add_argument("--show", type=int, default=None, metavar="INDEX", help="write one variant")
    p.add_argument("--small", action="store_true", help="with --show: the in-process sample's")
    args = p.parse_args(argv)

    if args.show is not None:
        v = make_variant(args.show, args.seed, mutation=args.only, small=args.small)
        folder = args.out / "variants"
        folder.mkdir(parents=True, exist_ok=True)
        feed = v.write(folder)
        print(v.label())
        print(f"expect: {v.expect}{'; pending: ' + v.pending if v.pending else ''}")
        print(f"supervisor {' '.join(feed.argv)}")
        return 0

    workdir = args.out / "variants"
    shutil.rmtree(workdir, ignore_errors=True)
    workdir.mkdir(parents=True)
    indexes = range(args.start, args.start + args.count)
    print(f"{len(indexes)} variants (seed {args.seed}), {args.jobs} at a time", flush=True)
    started = time.monotonic()
    records: list[Record] = []
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        futures = [
            pool.submit(
                _run_index, i, args.seed, args.only, workdir, args.timeout_s, args.memory_mb
            )
            for i in indexes
        ]
        for k, fut in enumerate(futures, start=1):
            records.append(fut.result())
            if k % 100 == 0:
                print(f"  {k} done", flush=True)
    wall_s = time.monotonic() - started
    cpu_s = sum(r.cpu_s for r in records)
    with (args.out / "results.jsonl").open("w", encoding="utf-8") as f:
        for r in records:
            f.write(json.dumps({**asdict(r), "category": r.category}, ensure_ascii=False) + "\n")
    shown = sys.argv[1:] if argv is None else argv
    report = write_report(records, args.out, args.seed, shown, wall_s, args.jobs, cpu_s)
    counts = collections.Counter(r.category for r in records)
    for name in CATEGORIES:
        print(f"{_SHORT[name]:<12} {counts[name]:>6}")
    print(f"{'total':<12} {len(records):>6}")
    failed = sum(r.failed for r in records)
    print(f"failures: {failed}; pending on other branches: {sum(r.excused for r in records)}")
    print(f"wall time: {wall_s:.0f} s; CPU time of the commands: {cpu_s:.0f} s")
    if records:
        slowest = max(records, key=lambda r: r.cpu_s)
        print(
            f"slowest command: {slowest.cpu_s:.1f} s of CPU (#{slowest.index}"
            f" {slowest.mutation}, {slowest.size_bytes:,} bytes); peak memory of any command:"
            f" {max(r.peak_mb for r in records):.0f} MB"
        )
    print(f"report: {report}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
