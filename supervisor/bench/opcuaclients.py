"""OPC UA clients in a process of their own (the load tests and ``supervisor bench opcua``
must not run clients on the loop they measure).

``python -m supervisor.bench.opcuaclients URL NAMESPACE --clients 20 --tags a,b,c --seconds 5``
connects every client at once, subscribes each to the tags, says ``subscribed`` on one
line when all are, counts the data changes each receives for ``--seconds``, then prints one
JSON line ``{"updates": [n per client], "errors": [...]}``. ``--seconds 0``: until killed.

``... --browse 10000 --seconds 20``: instead, one client that browses the server's address
space in a loop, as an engineer's OPC UA browser does node by node (issue 30's browse
row): a breadth-first walk from the Objects folder, one Browse request (hierarchical
references, forward) per node, a pass ending after 10,000 nodes (the walk starts over
from the Objects folder whenever the tree ends first). It says ``browsing`` once
connected, browses for ``--seconds``, then prints ``{"browsed": n, "passes": k,
"distinct": d, "errors": [...]}``.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import sys
from typing import Any

from asyncua import Client, ua


class Counter:
    def __init__(self) -> None:
        self.n = 0

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        self.n += 1

    def status_change_notification(self, status: Any) -> None:
        pass


async def one(
    url: str, uri: str, tags: list[str], counter: Counter, ready: asyncio.Event, stop: asyncio.Event
) -> None:
    client = Client(url, timeout=60)
    async with client:
        ns = await client.get_namespace_index(uri)
        sub = await client.create_subscription(50, counter)
        await sub.subscribe_data_change([client.get_node(ua.NodeId(t, ns)) for t in tags])
        ready.set()
        await stop.wait()


class Browsed:
    """What the browsing client did: Browse requests answered, whole passes, node ids."""

    def __init__(self) -> None:
        self.n = 0
        self.passes = 0
        self.seen: set[str] = set()


async def browse_pass(client: Client, nodes: int, browsed: Browsed) -> None:
    """One pass: ``nodes`` Browse requests, breadth first from the Objects folder (again
    from it whenever the tree ends first), each counted as it is answered."""
    objects = client.nodes.objects
    queue = [objects]
    for _ in range(nodes):
        if not queue:
            queue = [objects]
        node = queue.pop(0)
        refs = await node.get_references(
            refs=ua.ObjectIds.HierarchicalReferences, direction=ua.BrowseDirection.Forward
        )
        browsed.n += 1
        browsed.seen.add(node.nodeid.to_string())
        queue += [client.get_node(r.NodeId) for r in refs]
    browsed.passes += 1


async def browse(url: str, nodes: int, seconds: float) -> dict[str, Any]:
    """Browse passes of ``nodes`` nodes for ``seconds`` (the pass under way at the end
    counts its requests, not as a pass)."""
    browsed = Browsed()
    errors: list[str] = []
    client = Client(url, timeout=60)
    async with client:
        sys.stdout.write("browsing\n")
        sys.stdout.flush()

        async def passes() -> None:
            while True:
                await browse_pass(client, nodes, browsed)

        try:
            await asyncio.wait_for(passes(), timeout=seconds)
        except TimeoutError:
            pass
        except Exception as exc:  # said in the result, what was browsed kept
            errors.append(repr(exc))
    return {
        "browsed": browsed.n,
        "passes": browsed.passes,
        "distinct": len(browsed.seen),
        "errors": errors,
    }


async def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("url")
    p.add_argument("namespace")
    p.add_argument("--clients", type=int, default=1)
    p.add_argument("--tags", default="scan.count")
    p.add_argument("--seconds", type=float, default=5.0)
    p.add_argument("--browse", type=int, default=0, help="browse N nodes a pass instead")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    if args.browse:
        result = await browse(args.url, args.browse, args.seconds)
        sys.stdout.write(json.dumps(result) + "\n")
        return 0 if not result["errors"] else 1
    tags = args.tags.split(",")
    counters = [Counter() for _ in range(args.clients)]
    readies = [asyncio.Event() for _ in counters]
    stop = asyncio.Event()
    tasks = [
        asyncio.create_task(one(args.url, args.namespace, tags, c, r, stop))
        for c, r in zip(counters, readies, strict=True)
    ]
    all_ready: asyncio.Future[list[bool]] = asyncio.gather(*(r.wait() for r in readies))
    pending: list[asyncio.Future[Any]] = [all_ready, *tasks]
    await asyncio.wait(pending, return_when=asyncio.FIRST_COMPLETED)
    errors = [repr(t.exception()) for t in tasks if t.done() and t.exception() is not None]
    if not errors:
        sys.stdout.write("subscribed\n")
        sys.stdout.flush()
        base = [c.n for c in counters]
        if args.seconds > 0:
            await asyncio.sleep(args.seconds)
        else:
            await asyncio.Event().wait()  # until killed
        got = [c.n - b for c, b in zip(counters, base, strict=True)]
    else:
        all_ready.cancel()
        got = [c.n for c in counters]
    stop.set()
    results = await asyncio.gather(*tasks, return_exceptions=True)
    errors += [repr(r) for r in results if isinstance(r, BaseException) and repr(r) not in errors]
    sys.stdout.write(json.dumps({"updates": got, "errors": errors}) + "\n")
    return 0 if not errors else 1


if __name__ == "__main__":
    sys.exit(asyncio.run(main(sys.argv[1:])))
